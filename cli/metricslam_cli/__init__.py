"""Command line: ``metricslam <subcommand>`` (console script ``metricslam = metricslam_cli.main:main``).

The top floor but bench (docs/architecture.md): it may import the core, the services and
training, and nothing imports it. Each subcommand is one module here with
``add_parser(subparsers)``; only argparse-level things are imported at module level, so
``metricslam --help`` stays fast, and the heavy imports (services, training, torch) happen inside
the command's ``run``.
"""
