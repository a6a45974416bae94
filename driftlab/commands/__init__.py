"""CLI subcommands: one module per subcommand group, each exposing ``register(subparsers)``.

``driftlab.cli`` discovers every module in this package, so adding a subcommand
never means editing a shared file. A module registers one or more subcommands
and sets ``func`` on each parser via ``set_defaults(func=...)``; the function
takes the parsed ``argparse.Namespace`` and returns an exit status.
"""
