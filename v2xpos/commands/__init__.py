"""Command-line subcommands that compose services and tools (the top floor; ``v2xpos.cli`` maps
names to modules)."""
