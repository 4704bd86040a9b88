"""The documentation ``absorption`` and ``normalise_reference`` share (:mod:`selpath.stages.tomography.calibrate`):
their settings, and what they return besides their result, written once and put into both docstrings."""

PAIR_DOCS = """Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` store (or one with its ``target``, ``reference`` and ``dark`` frames over
        (angle, row, col) [counts]; ``backlit`` optional, for the background flag), raw or dark-subtracted.
    silhouettes : xr.Dataset or None
        A ``silhouettes`` store of this capture (input, optional): its masks say which pixels are the object's,
        so the frames are thresholded once, by the stage the visual hull reads, and the two cannot disagree
        (a workflow wires ``silhouettes: $silhouettes``); None: masks made here from ``backlit``.
    saturation_level : float or None
        Raw count at or above which a pixel is saturated [counts]; default: the capture's
        ``saturation_counts`` attr (``saturation_level`` in stores of format ≤ 5), else the integer dtype's maximum.
    min_signal : float
        Dark-subtracted count at or below which a pixel has no usable signal [counts].
    min_signal_relative : float
        Also no usable signal at or below this share of the frame's brightest unsaturated reference pixel
        (dark-subtracted) [1]: a threshold meaningful on any intensity scale (radiance renders, 16-bit
        cameras); 0 turns it off. A pixel must pass both.
    flag_background : bool
        With ``backlit`` frames in the capture, flag pixels off the object ``background`` (bit 64, NaN): those
        outside the silhouette of the backlit frame at that angle (where the object does not hide the lit
        plane; the ``silhouettes`` stage's kernel and ``min_size``), whose target and reference are both the
        dark level and whose log difference is noise. Without backlit frames no pixel is flagged background,
        nor where a backlit value is NaN or inf (a frame never filmed: nothing says the pixel is off the
        object). False: none is.
    silhouette_threshold : float or None
        Backlit counts above dark below which a pixel is on the object, as the ``silhouettes`` stage's
        ``threshold`` (give both the same); None: Otsu's threshold per frame [counts]. Not with ``silhouettes``."""

#: what absorption and normalise_reference return besides their result and ``flags`` (their Returns sections)
PAIR_SHARES = """the usable shares ``signal_fraction`` (the object's pixels whose reference has usable
        signal; floor 0.1 %), ``usable_fraction`` (of those, pixels whose target is usable too; floor 5 %) and
        ``dark_fraction`` (dark pixels ≥ 0 counts; floor 5 %): below a floor the workflow stops, naming the cause
        (:mod:`selpath.pipeline.quality`). The object's pixels are those not flagged background (every pixel
        without backlit frames). Two informative 0-d variables, never checked against a floor, say what a summary
        of the object needs: ``object_valid_fraction`` (the object's pixels that are valid) and
        ``background_fraction`` (pixels flagged background). Unsorted angles are sorted (with a warning).

    Raises
    ------
    StageError
        A repeated angle, or a share below its floor (when the engine computes it)."""


def pair_docs(func):
    """The settings' documentation shared by absorption and normalise_reference (read by the registry)."""
    func.__doc__ = func.__doc__.replace("{pair}", PAIR_DOCS).replace("{shares}", PAIR_SHARES)
    return func
