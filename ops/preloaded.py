"""Imported last by the fork server (:mod:`wavegrasp.ops.forked`), after every service's
modules: it freezes what those imports made (``gc.freeze``), so each fork's collections,
its start-up one included (:func:`wavegrasp.runtime.service.freeze_startup_objects`), skip
those objects instead of walking them (and copying their pages) in every service. Before
that, the messages' CDR code is generated once for all (:func:`wavegrasp.schemas.ros.warm_up`)."""

import gc

from wavegrasp.schemas.ros import warm_up

warm_up()
gc.collect()
gc.freeze()
