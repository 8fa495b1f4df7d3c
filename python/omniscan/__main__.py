"""The ``omniscan`` command, as the wheel installs it: the same command line
as the Rust binary, run in this process (``python -m omniscan ...``)."""

import sys

from . import _omniscan


def main() -> None:
    sys.exit(_omniscan.run_cli(["omniscan", *sys.argv[1:]]))


if __name__ == "__main__":
    main()
