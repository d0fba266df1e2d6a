"""Headless commands: ``procam …`` in the venv and ``blender --background --command procam …``.

``app`` parses the command line and turns errors into exit codes; ``terminal`` draws progress and catches
Ctrl-C; every other module is one subcommand: argparse → the step's Options → ``addon.steps`` → a summary on
stdout. No command computes or writes anything itself.
"""
