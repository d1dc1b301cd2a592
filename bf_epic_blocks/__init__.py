"""bf_epic_blocks: exact wide-field E-field imaging blocks for Bifrost pipelines.

Three rooms:

* :mod:`bf_epic_blocks.imaging` -- the math: pure functions on NumPy or CuPy arrays.
* :mod:`bf_epic_blocks.blocks` -- thin Bifrost blocks (on real Bifrost or :mod:`bf_epic_blocks.runtime`).
* :mod:`bf_epic_blocks.pipeline` -- YAML pipelines, LSL station metadata, sources, outputs and the CLI.

Conventions (sign, axes, normalisation) are stated once in ``docs/CONVENTIONS.md`` and in
:mod:`bf_epic_blocks.conventions`.
"""
__version__ = "0.1.0"
