"""Pipeline room: YAML pipeline configs, LSL station metadata, simulated sky, FITS/PNG outputs, CLI.

Modules: :mod:`.config` (schema + validation), :mod:`.fits_out` (FITS cubes and pixel tables),
:mod:`.quicklook` (PNG quicklooks); the others are added as the pipeline grows.
"""
