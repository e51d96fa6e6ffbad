"""The house's shared infrastructure, used by every package (no optics here).

- ``cli``: the ``doefab`` dispatcher (the only importer of command modules)
- ``errors``: InputError (exit code 2)
- ``files``: staged, atomic writing and safe reading of the contract files
- ``flags``: range checks of numeric command-line flags
- ``image_pages``: pages of an image file, a quiet libpng
- ``interrupts``: Ctrl-C and SIGTERM, remembered as well as raised
- ``png``: PNG figures without a version stamp (the same bytes for the same figure)
"""
