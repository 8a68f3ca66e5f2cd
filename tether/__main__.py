"""`python -m tether` and the `tether` script: the whole CLI, except that `run SERVICE` loads only that service.

A systemd unit or a container runs `tether run SERVICE`; through `main` it loads tether.runservice
and that service's package, never tether.cli (whose other commands pull in mcap, rich, pinocchio ...).
"""

import sys


def main() -> None:
    """The `tether` script's entry point (pyproject.toml [project.scripts]); exits with the command's code."""
    from tether.runservice import runs_a_service

    if runs_a_service(sys.argv[1:]):
        from tether.runservice import app
    else:
        from tether.cli import app
    app()


if __name__ == "__main__":
    main()
