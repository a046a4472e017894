"""Settings of the ceiling-lamp detector (paper 1, eqs. 1-7; DESIGN.md sec. 1).

One frozen dataclass read by every stage of the detector: the threshold
(:mod:`lampsam.frontend.threshold`), the per-blob checks and coverage moments
(:mod:`lampsam.frontend.blob_moments`), glare splitting
(:mod:`lampsam.frontend.glare`) and the conversion to ceiling coordinates
(:mod:`lampsam.frontend.ceiling_coords`). Pixel sizes are for 320x240 frames
(:func:`lampsam.frontend.resolution.lamp_config_for_width` scales them).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LampDetectorConfig:
    """Settings of the lamp detector.

    Attributes:
        threshold: the paper's fixed grey-level threshold ``k`` (pixels ``> k``
            are lamp); None (default) chooses it per image with
            :func:`auto_threshold`.
        max_bright_fraction: automatic threshold: Otsu is re-applied to the
            upper class while more than this fraction of the image lies above
            the threshold (default 0.08: lamps are a small part of a ceiling).
        light_share: automatic threshold: the repeated Otsu also stops when
            at least this fraction of the pixels above the threshold are at a
            light source's level (``>= peak - max_peak_drop_grey``, the level the
            blobs' dimness test asks of a lamp; clipped, 255, when that test is
            off): such an upper class is light sources (lamps, a bright window),
            not ceiling, and a further Otsu step would only split the brightest
            lights from the others (a window covering 10 % of a frame otherwise
            drives ``k`` to 243-254, above fluorescent tubes at 190-250; default
            0.5: most of it; None: the rule before).
        max_otsu_iterations: automatic threshold: at most this many Otsu steps
            (default 4).
        min_contrast_grey: below this grey-level spread between the image's
            median and its maximum there are no lamps (all black, all white,
            flat images; default 30).
        min_relative_level: the automatic threshold is at least
            ``median + min_relative_level (peak - median)``, ``peak`` being the
            brightest level reached by ``min_area_px`` pixels: lamps are the
            brightest things on a ceiling, and mid-grey panels are not lamps
            (default 0.5).
        min_blob_contrast_grey: a blob whose level (median inside) is less
            than this above its background ring is not a lamp (specular
            highlights on bright ducts; default 30).
        max_peak_drop_grey: a blob whose fifth-brightest pixel is more than this
            below the image's lamp peak (the brightest level reached by
            ``min_area_px`` pixels) is not a lamp: lamps are light sources and
            saturate or nearly, specular highlights on ducts and walls are
            dimmer (default 15; None disables).
        max_peak_drop_thin_grey: the same for blobs thinner than
            ``thin_width_px``, whose brightest pixel area sampling dims
            (default 25).
        max_crowding: a blob whose reach (``support_px + ring_px`` around
            it) is covered by other thresholded pixels for more than this
            fraction of its background ring is not a lamp: the panes of a
            skylight or window are ringed by thin glazing bars with the
            neighbouring panes just beyond, a lamp by plain ceiling
            (default 0.2; None disables).
        size_gate: per lamp model ``(min_area, max_area, ratio)`` on the
            ceiling (areas in m^2 per m^2 of height) when the ceiling's lamp
            models are known (:func:`lampsam.frontend.lamp_models.size_gate_from_models`):
            blobs matching no model are not lamps; None (default): no check.
        thin_width_px: short-axis width ``sqrt(12 lambda_min)`` below which a
            blob is thin (default 3 px).
        thin_min_length_px: a thin blob's brightest pixel gets the wider
            margin ``max_peak_drop_thin_grey`` only when its long-axis extent
            ``sqrt(12 lambda_max)`` is at least this (a line: a lamp seen
            edge-on); a thin blob shorter than this is small both ways and its
            brightest pixel gets ``max_peak_drop_grey`` (a white smoke detector
            2-3 px across in a 160x120 frame is not a lamp; default 6 px, twice
            ``thin_width_px``; 0: every thin blob gets the wider margin, the
            rule before).
        min_area_px: smaller blobs are rejected (default 6).
        max_area_fraction: blobs larger than this fraction of the image are
            rejected (glare, a window; default 0.2).
        ratio_threshold: ``R_ori`` above which a lamp is oriented (default 1.5, the paper's).
        support_px: the moments are taken inside the blob dilated by this many
            pixels, so that anti-aliased edge pixels below ``k`` count (default 2).
        ring_px: width of the background ring outside the support (default 3).
        noise_floor_grey: lower bound on the grey-level noise sigma (default 1.0).
        sigma_centroid_floor_px: model-error floor on the centroid sigma
            (default 0.05 px).
        sigma_axis_floor: model-error floor on the axis sigma, rad (default 0.002).
        min_fill: a blob filling less of its moment ellipse is a glare merger
            candidate (default 0.85).
        jacobian_step_px: step of the central differences for ``dm/dpx``
            (default 0.5 px).
        saturated_edges: read the edge pixels of saturated lamps with the clip
            coverage measured on the image (:mod:`lampsam.frontend.saturated_edges`;
            default True; False: the coverage weights as read).
        saturated_edge_min_steps: fewest clipped-to-background steps on an image
            for the clip coverage to be measured (default 16).
        edge_phase_noise: add to an oriented saturated blob's centroid covariance the
            error its straight edges keep from the clip (:mod:`lampsam.frontend.lamp_noise`:
            largest when the edges are parallel to the pixel grid); default False (the
            floor alone).
    """

    threshold: int | None = None
    max_bright_fraction: float = 0.08
    light_share: float | None = 0.5
    max_otsu_iterations: int = 4
    min_contrast_grey: float = 30.0
    min_relative_level: float = 0.5
    min_blob_contrast_grey: float = 30.0
    max_peak_drop_grey: float | None = 15.0
    max_peak_drop_thin_grey: float = 25.0
    max_crowding: float | None = 0.2
    size_gate: tuple[tuple[float, float, float], ...] | None = None
    thin_width_px: float = 3.0
    thin_min_length_px: float = 6.0
    min_area_px: int = 6
    max_area_fraction: float = 0.2
    ratio_threshold: float = 1.5
    support_px: int = 2
    ring_px: int = 3
    noise_floor_grey: float = 1.0
    sigma_centroid_floor_px: float = 0.05
    sigma_axis_floor: float = 0.002
    min_fill: float = 0.85
    jacobian_step_px: float = 0.5
    saturated_edges: bool = True
    saturated_edge_min_steps: int = 16
    edge_phase_noise: bool = False


DEFAULT_CONFIG = LampDetectorConfig()  # frozen: one shared instance
