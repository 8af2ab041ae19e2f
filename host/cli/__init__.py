"""The upright command line: one module per command, dispatched by host.cli.main."""
