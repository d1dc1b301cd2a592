"""The package's own Bifrost-compatible ring runtime (used when ``import bifrost`` fails).

It implements the subset of ``bifrost.pipeline`` / ``bifrost.ring2`` that our blocks use, with
Bifrost's names, hook signatures and header format (see ``docs``/BIFROST.md):

* :mod:`.pipeline` -- ``Pipeline``, ``block_scope``, ``get_default_pipeline``, ``SourceBlock``,
  ``TransformBlock``, ``SinkBlock``, ``MultiTransformBlock``; one thread per block.
* :mod:`.ring` -- bounded rings of sequences in the 'system' (NumPy) or 'cuda' (CuPy) space,
  guaranteed (back-pressure) and unguaranteed (overrun -> skips) readers.
* :mod:`.dtypes` -- Bifrost type strings, storage forms, ``unpack_complex``/``pack_ci4``.
* :mod:`.header` -- header validation.

Spans are views of ring memory, as in Bifrost (guaranteed readers and writers); on the GPU each
block thread has its own CUDA stream and rings order them with CUDA events (no device-wide
synchronisation). Differences from Bifrost (deliberate): an exception in any block stops the
whole pipeline and ``Pipeline.run()`` raises :class:`PipelineError` naming the block; every block
keeps counters in ``block.stats``; unguaranteed readers get copies taken under the ring lock
(``nframe_overwritten`` is always 0).
"""
from . import dtypes, header, ring, pipeline  # noqa: F401
from .dtypes import unpack_complex, pack_ci4, pack_complex, storage_dtype  # noqa: F401
from .header import HeaderError, validate_header, split_shape  # noqa: F401
from .ring import Ring, PipelineShutdown  # noqa: F401
from .pipeline import (  # noqa: F401
    Pipeline, PipelineError, BlockScope, block_scope, get_default_pipeline,
    get_current_block_scope, get_ring, Block, SourceBlock, MultiTransformBlock,
    TransformBlock, SinkBlock,
)

__all__ = ['dtypes', 'header', 'ring', 'pipeline', 'unpack_complex', 'pack_ci4', 'pack_complex',
           'storage_dtype', 'HeaderError', 'validate_header', 'split_shape', 'Ring',
           'PipelineShutdown', 'Pipeline', 'PipelineError', 'BlockScope', 'block_scope',
           'get_default_pipeline', 'get_current_block_scope', 'get_ring', 'Block', 'SourceBlock',
           'MultiTransformBlock', 'TransformBlock', 'SinkBlock']
