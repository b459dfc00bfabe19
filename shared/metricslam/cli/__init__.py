"""Command line: ``metricslam <subcommand>``. Each subcommand is one module here with
``add_parser(subparsers)``; heavy imports happen inside the command's ``run``."""
