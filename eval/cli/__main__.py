"""`python -m conav_jax.eval.cli`: the `conav` command."""

import sys

from conav_jax.eval.cli import main

sys.exit(main())
