"""Re-export of `pa_cli.geometry.exp_so3` for `pa_cli/adjust/synthetic.py`, which imports it from here."""

from pa_cli.geometry import exp_so3

__all__ = ["exp_so3"]
