"""The host link: the message table as typed messages, serial and CAN clients, the generated DBC and protocol reference."""
