"""The machinery under everything else: errors and exit codes, argument checks, atomic files,
array helpers, the export cache and every use of a private API of jax, equinox or diffrax."""
