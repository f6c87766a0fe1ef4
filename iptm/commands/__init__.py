"""One module per ``iptm`` subcommand, each with ``register(subparsers)``."""
