"""Client-side ``facecast`` subcommands: ``add_arguments(parser)`` and ``run(args) -> int``."""
