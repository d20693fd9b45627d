"""The application layer: workflows that drive the pipeline end to end. Nothing below this layer imports it
(``tests/test_package.py``, ``LAYERS``).

:mod:`.export` (a frame sequence from our path tracer), :mod:`.sequence` (``reproject`` over a frame-sequence
directory), :mod:`.diagnose` (convention mistakes in a sequence, before it is reprojected), :mod:`.experiment`
(the paper's experiment). The file formats they read and write are in :mod:`stereorepro.io`.
"""
