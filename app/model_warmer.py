"""Loads newly ready models and builds their search structures in the background.

A learned model is stored on disk by a job process; the API process first
meets it when a localization asks for it. That request would pay for loading
the files and for everything the localizer derives from a model (alignment
index, view templates, contour model, surface samples: 0.3-0.5 s for the
bench parts) instead of the tens of milliseconds the rest take. The warmer
polls the store for ready models it has not seen (at start-up: those already
stored; later: those a job has just learned or relearned, by whichever
runner), loads them into the store's cache and prepares them.

Its first look comes at start-up, and until it has finished the service
is not ready (``/readyz``): a station that starts sending as soon as the
service says ready would otherwise wait for the preparation of the model
it asks for (first localization after a restart, hard bench set's
bracket: 815 ms against about 70 ms).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from app.periodic import Periodic
from model_store import CorruptModelError, ModelStore, StoreError

log = logging.getLogger("viewloc.warmer")


class ModelWarmer:
    """Keeps the newest ready models loaded and prepared.

    Parameters
    ----------
    store : ModelStore
        The store whose cache the models are loaded into.
    prepare : callable
        Builds a loaded model's derived structures (:func:`viewloc_core.localize.prepare`).
    limit : int
        Most models prepared at once: the newest ``limit`` ready objects. The
        store's cache size, so that warming never evicts what it just warmed.
    interval_s : float
        Seconds between looks at the store (one indexed query each).
    """

    def __init__(self, store: ModelStore, prepare: Callable[[Any], None], limit: int,
                 interval_s: float = 1.0) -> None:
        self.store, self.prepare, self.limit = store, prepare, max(0, int(limit))
        self.interval_s = interval_s
        #: (object id, model digest) of every model already prepared (or
        #: found unloadable), so that each stored model is handled once.
        self._seen: set[tuple[str, str]] = set()
        self._loop: Periodic | None = None
        self._first_pass = threading.Event()
        if self.limit == 0:
            self._first_pass.set()

    @property
    def warm(self) -> bool:
        """Whether the models ready when polling began have been prepared
        (or found unloadable); always True when warming is off."""
        return self._first_pass.is_set()

    def start(self) -> None:
        """Start polling in a daemon thread, the first look at once (a no-op
        when ``limit`` is 0)."""
        if self._loop is not None or self.limit == 0:
            return
        self._loop = Periodic("viewloc-model-warmer", self.interval_s, self.step,
                              immediately=True)
        self._loop.start()

    def stop(self) -> None:
        """Stop polling (a model being prepared is finished first)."""
        if self._loop is not None:
            self._loop.stop()
            self._loop = None

    def step(self) -> list[str]:
        """Load and prepare the ready models not seen yet, newest first.

        Returns
        -------
        list of str
            The object ids prepared by this call.
        """
        if self.limit == 0:
            return []
        ready = [r for r in self.store.list_objects("ready") if r.model_sha256 is not None]
        newest = ready[::-1][: self.limit]
        current = {(r.object_id, str(r.model_sha256)) for r in newest}
        # Forget deleted and relearned models, so the set stays as small as the cache.
        self._seen &= current
        prepared = []
        for record in newest:
            key = (record.object_id, str(record.model_sha256))
            if key in self._seen:
                continue
            self._seen.add(key)
            t = time.perf_counter()
            try:
                model = self.store.load_model(record.object_id)
                self.prepare(model)
            except (StoreError, CorruptModelError) as exc:
                # Deleted or relearned meanwhile, or corrupt (the store has
                # marked it failed): a request will get the same answer.
                log.info("model of %s not prepared: %s", record.object_id, exc)
                continue
            prepared.append(record.object_id)
            log.info("model of %s prepared in %.0f ms", record.object_id,
                     (time.perf_counter() - t) * 1000)
        # Only a pass that went through every model counts: one cut short by
        # an error is taken up again by the next.
        self._first_pass.set()
        return prepared
