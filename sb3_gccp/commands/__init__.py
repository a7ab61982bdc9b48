"""The commands of ``sb3_gccp``, one module each: ``add_parser`` declares its options and ``run`` runs it.

:mod:`sb3_gccp.cli` dispatches to them; :mod:`~sb3_gccp.commands.common` holds what several share.
Each command imports what it runs when it runs, so that ``sb3_gccp --help`` stays quick.
"""
