"""The command line: one module per command, the only place that writes run folders."""
