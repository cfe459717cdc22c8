"""PyTorch (openpi PyTorch port / LeRobot) π0 / π0.5 checkpoints -> pi0-jax checkpoints. No torch needed.

Layout: `source.py` finds and reads the tensors (lazily), `detect.py` decides which model they are, `table.py`
is the declarative key/shape/transform table, `convert.py` drives it, `cli.py` is the `convert` subcommand.
"""

from converters.convert import convert
from converters.errors import ConversionError

__all__ = ["ConversionError", "convert"]
