"""One module per ``facecast`` subcommand: ``add_arguments(parser)`` and ``run(args) -> int``."""
