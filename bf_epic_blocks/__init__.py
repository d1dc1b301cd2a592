"""bf_epic_blocks: exact wide-field E-field imaging blocks for Bifrost pipelines.

Rooms, each importing only the rooms below it (tests/test_layering.py holds the tree to this)::

    pipeline/   YAML schema, config -> graph of blocks, the bf-epic CLI
    blocks/  service/
                thin Bifrost adapters (DFTImagerBlock, WStackBlock, CalFoldBlock, sources, writers);
                the running pipeline's metrics and health over HTTP (`bf-epic run --serve`)
    station/  sky/  io/  runtime/
                LSL station tables and offline set-up; catalogue sources, astropy directions and
                the simulated E-field; readers (TBF) and writers (FITS, PNG); the ring runtime
    imaging/    the math: pure functions on NumPy or CuPy arrays
    conventions.py  sign, axes and normalisation, stated once (docs/CONVENTIONS.md)

The three user-facing blocks are importable from the top level
(``from bf_epic_blocks import DFTImagerBlock, WStackBlock, CalFoldBlock``); they load on first use,
so ``from bf_epic_blocks import imaging`` does not pull in the block runtime.
"""
__version__ = "0.4.0"

_BLOCKS = ("DFTImagerBlock", "WStackBlock", "CalFoldBlock")

__all__ = ["__version__", *_BLOCKS]


def __getattr__(name):  # PEP 562: lazy, so the math stays importable without the block layer
    if name in _BLOCKS:
        from . import blocks
        return getattr(blocks, name)
    raise AttributeError(f"module 'bf_epic_blocks' has no attribute {name!r}")
