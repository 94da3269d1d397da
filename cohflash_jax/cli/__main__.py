"""`python -m cohflash_jax.cli`: the `cohflash` command."""

import sys

from . import main

sys.exit(main())
