"""One module per ``streaklab`` subcommand; each defines ``add_arguments(parser)`` and ``run(args) -> int``."""
