"""The blocks room: thin Bifrost blocks over the math in :mod:`bf_epic_blocks.imaging`.

They run unchanged inside real Bifrost (when ``import bifrost`` works) or on the package's own ring
runtime (:mod:`bf_epic_blocks.runtime`); :mod:`._compat` picks. Header keys: docs/HEADERS.md.

Importing them changes nothing in Bifrost. Inside real Bifrost our reading blocks trim their own
read spans to whole frames after an overrun; :func:`enable_bifrost_compat` does the same for every
Bifrost block of the process, for pipelines that mix our blocks with others (see its docstring).
"""
from ._compat import HAVE_BIFROST, RUNTIME, bfp, enable_bifrost_compat  # noqa: F401
from .array_io import ArraySinkBlock, ArraySourceBlock, array_sink, array_source  # noqa: F401
from .calfold import CalFoldBlock, cal_fold  # noqa: F401
from .cube_writer import ImageCubeWriterBlock, image_cube_writer  # noqa: F401
from .dft_imager import DFTImagerBlock, dft_imager  # noqa: F401
from .gain_solver import GainSolverBlock, LiveGainTable, gain_solver  # noqa: F401
from .headers import efield_header, efield_layout, image_layout  # noqa: F401
from .integrate import ImageIntegratorBlock, image_integrator  # noqa: F401
from .pixel_merge import PixelMergeBlock, pixel_merge  # noqa: F401
from .transient_search import TransientSearchBlock, transient_search  # noqa: F401
from .wstack import WStackBlock, wstack  # noqa: F401
