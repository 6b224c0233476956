"""Imported last by the fork server (:mod:`wavegrasp.ops.forked`), after every service's
modules: it freezes what those imports made (``gc.freeze``), so each fork's collections,
its start-up one included (:func:`wavegrasp.runtime.service.freeze_startup_objects`), skip
those objects instead of walking them (and copying their pages) in every service."""

import gc

gc.collect()
gc.freeze()
