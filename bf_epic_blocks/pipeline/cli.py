"""The ``bf-epic`` command line (placeholder until the pipeline commands land)."""
import argparse
import sys

from .. import __version__


def build_parser():
    p = argparse.ArgumentParser(prog="bf-epic", description="Exact wide-field E-field imaging pipelines.")
    p.add_argument("--version", action="version", version=f"bf-epic {__version__}")
    return p


def main(argv=None):
    build_parser().parse_args(argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
