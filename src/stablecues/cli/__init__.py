"""Command-line interface: the only package that sees argparse."""
