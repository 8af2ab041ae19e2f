"""The firmware build room: the viper/native variants of the firmware's hot code, generated from its readable Python by an AST transform."""
