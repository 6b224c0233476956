"""``wavegrasp predictor``: where the object will be, from now to at least one wave period ahead.

Models are plain classes with ``update(t_s, position) -> Forecast | None``: ``linear`` (the
paper's constant-velocity baseline), ``harmonic`` (the paper's equations 1-7) and ``blend`` (the
default: direct multi-step regression on lagged positions combined with the harmonic model).
"""

#: The motion models ``wavegrasp predictor`` offers (:mod:`wavegrasp.predictor.models`): named
#: here so that choosing one (``wavegrasp up --predictor``) need not import them.
MODELS = ("blend", "harmonic", "linear")
DEFAULT_MODEL = "blend"
