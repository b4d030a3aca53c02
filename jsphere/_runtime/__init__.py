"""The machinery under everything else: errors and exit codes, argument checks, atomic files,
array helpers, float precision (`enable_x64`, `PrecisionWarning`), the export cache and every
use of a private API of jax, equinox or diffrax."""
