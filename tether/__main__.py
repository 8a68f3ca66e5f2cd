"""`python -m tether`: the same CLI as the `tether` script."""

from tether.cli import app

app()
