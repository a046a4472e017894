"""lampsam.frontend: Images -> measurements: ceiling lamps (paper 1, eqs. 1-7), FAST corners with NCC,
and stereo tracking.

Entry points (loaded on first use)::

    process_image     lamps and corners of one ceiling image (pipeline)
    iter_run          the frontend over a run, frame by frame (pipeline)
    FrontendConfig    frontend settings (pipeline)
    detect_lamps      lamp blobs of one image (lamps)
    detect_corners    FAST corners of one image (corners)

Modules:

* :mod:`~lampsam.frontend.blob_moments` -- Coverage-weighted moments of lamp blobs, with their uncertainty (paper 1, eqs. 2-7).
* :mod:`~lampsam.frontend.blob_reach` -- The pixels within reach of the labelled lamp blobs of a box, gathered in one pass.
* :mod:`~lampsam.frontend.ceiling_coords` -- Pixel measurements of lamps -> normalised ceiling coordinates (docs/conventions.md).
* :mod:`~lampsam.frontend.ceiling_grid` -- Blob moments taken on the ceiling: a per-pixel table of ``m`` for lenses that bend lamps (fisheye).
* :mod:`~lampsam.frontend.corners` -- FAST corners on the ceiling and normalised cross-correlation (NCC) matching.
* :mod:`~lampsam.frontend.dilation` -- Dilation by an elliptic disk, done as a chain of cheaper footprints.
* :mod:`~lampsam.frontend.glare` -- Separating lamps that a saturated glare halo has merged into one blob.
* :mod:`~lampsam.frontend.label_stats` -- Connected-component labelling and per-label statistics over pixel lists.
* :mod:`~lampsam.frontend.lamp_config` -- Settings of the ceiling-lamp detector (paper 1, eqs. 1-7; DESIGN.md sec. 1).
* :mod:`~lampsam.frontend.lamp_models` -- Lamp size against the lamp models a ceiling is known to carry, so that daylight is not taken for a lamp.
* :mod:`~lampsam.frontend.lamp_noise` -- Per-observation centroid noise of a lamp from its straight edges' alignment with the pixel grid.
* :mod:`~lampsam.frontend.lamps` -- Ceiling-lamp detection on one grey image: the stages of paper 1, eqs. 1-7, in order.
* :mod:`~lampsam.frontend.measurements` -- Frozen measurement dataclasses: what the frontend hands to the backends.
* :mod:`~lampsam.frontend.pipeline` -- The ceiling frontend: one grey image in, one :class:`CeilingFrame` out.
* :mod:`~lampsam.frontend.resolution` -- The working resolution of a high-resolution photo, chosen from what the lamp detector must resolve.
* :mod:`~lampsam.frontend.saturated_edges` -- Coverage of the edge pixels of saturated lamps: a clipped pixel is not a covered pixel.
* :mod:`~lampsam.frontend.second_look` -- A second, finer look inside lamp blobs that are long for their frame (two lamps end to end).
* :mod:`~lampsam.frontend.stereo_tracking` -- Corner tracking and left-right matching on rectified stereo sequences (KITTI).
* :mod:`~lampsam.frontend.threshold` -- The lamp threshold ``k`` of paper 1, eq. 1, chosen per image from its grey-level histogram.
"""

from lampsam._lazy import lazy_exports

__getattr__, __dir__ = lazy_exports(__name__, {
    "process_image": "lampsam.frontend.pipeline",
    "iter_run": "lampsam.frontend.pipeline",
    "FrontendConfig": "lampsam.frontend.pipeline",
    "detect_lamps": "lampsam.frontend.lamps",
    "detect_corners": "lampsam.frontend.corners",
})
