"""`python -m cohflash_jax.cli`: the `cohflash` command."""

from . import entry

entry()
