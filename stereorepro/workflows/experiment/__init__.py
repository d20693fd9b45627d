"""The paper's experiment (§4) as one command: effective spp, Tables 1–2, Figures 1/3/4, and the time cost.

For every frame of a scene's camera path, both eyes are rendered by :class:`~stereorepro.PathTracer`:

* G-buffers (one unjittered primary ray per pixel),
* a **ladder** of plain path-traced images at 1..L spp — prefixes of one sample stream (sample indices 0..L-1),
* a **reference** at R spp from a disjoint stream (sample indices from :data:`REFERENCE_OFFSET`).

The 1-spp rung of each eye is the renderer's 1-spp input. The schemes then run on those inputs
(:class:`~stereorepro.SpatiotemporalReprojection`):

* ``stereo``: right eye at 1 spp reprojected into the left eye; the left eye's discarded pixels traced at 1 spp;
  evaluated on the left eye;
* ``temporal``: the right eye accumulated over time (EMA, 20 %); evaluated on the right eye;
* ``stereo_temporal``: temporal on the right eye, stereo R → L, left-eye temporal filling; evaluated on the left.

Metric: RMSE of images clamped to [0, 1] by default (``metric="ldr"``, display-referred), or of linear radiance
(``"hdr"``). Under HDR RMSE, antialiased edges of directly visible emitters (radiance ≈ 5–6 beside ≈ 0.2) dominate
the error of any resampling scheme: on the Living Room the stereo scheme fed with *noise-free* references still has
an HDR RMSE equal to 16-spp noise, so effective spp stays near 1–3 whatever the noise reduction. The paper does not
say which it used; its numbers fit display-referred images. Both are one flag apart; the README reports both.

Variants (nearest sampling, other alphas) run on the same renders, so what each step of accuracy costs shows
side by side. Quality is RMSE against the reference turned into effective spp with the eye's ladder
(:mod:`stereorepro.measure.metrics`); matching against a ladder scored on the same reference cancels the reference's
own noise to first order.

Renders are cached by content (scene file, mesh file, frame, eye, sample range, resolution, seed, renderer source),
written atomically, so a killed run resumes and a cached run reproduces the same tables; ``force`` recomputes.

Resolution and thresholds: scene thresholds (in scene units, like the paper's scene-specific limits) follow the
package's one rule, :func:`stereorepro.scenes.threshold_scale` (scaled up below 180 rows, used as they are above).

Renders can run on a Dask cluster (``scheduler="local:N"`` or ``"tcp://HOST:PORT"``, :mod:`.distributed`): every
render is a task named by its cache entry, and the tables are identical to an in-process run's.

Layout: :mod:`.config` (settings and schemes), :mod:`.cache` (the content-addressed render cache),
:mod:`.inputs` (the render tasks: one frame's G-buffers, lean ladder and reference chunks),
:mod:`.distributed` (the same tasks on Dask), :mod:`.run` (the run loop),
:mod:`.report` (tables, figures, report); the command line is :mod:`stereorepro.cli.experiment`.
"""

from .cache import RenderCache
from .config import REFERENCE_OFFSET, SCHEMES, THRESHOLD_ROWS, ExperimentConfig, Scheme
from .report import cost_markdown, tables_markdown
from .run import ExperimentResults, run_experiment

__all__ = [
    "ExperimentConfig",
    "ExperimentResults",
    "run_experiment",
    "REFERENCE_OFFSET",
    "SCHEMES",
    "Scheme",
    "THRESHOLD_ROWS",
    "RenderCache",
    "tables_markdown",
    "cost_markdown",
]
