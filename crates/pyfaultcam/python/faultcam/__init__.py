"""faultcam: physically modelled camera faults on numpy arrays.

>>> import faultcam, numpy as np
>>> chain = faultcam.Chain.from_toml("faults.toml", seed=7)
>>> out, record = chain.apply(np.zeros((480, 640), np.uint8), frame_index=0)

``Chain.apply`` gives the bytes ``faultcam apply`` writes for the file with index
``frame_index`` of a folder, for the same config and seed. Images are uint8 (H, W), (H, W, 1)
or (H, W, 3) RGB, or uint16 (H, W) / (H, W, 1); the GIL is released while the chain runs, so
threads applying separate chains run in parallel. Like ``faultcam apply``, the config's
campaign timeline (``[[events]]``) is not run unless ``timeline=True`` is given to
``Chain.from_toml`` (then as ``faultcam run`` on a ``files:`` source at ``fps``).
"""

from __future__ import annotations

import json

import numpy as np

from ._faultcam import Chain as _Chain
from ._faultcam import __version__
from ._faultcam import effects as _effects

__all__ = ["Chain", "effects", "FaultcamTransform", "__version__"]


class Chain:
    """A fault chain loaded from a faultcam fault config (TOML)."""

    def __init__(self, inner: _Chain):
        self._inner = inner
        self._next = 0

    @classmethod
    def from_toml(cls, path, seed: int | None = None, timeline: bool = False, fps: float = 30.0) -> "Chain":
        """Load ``path`` (as ``faultcam apply --faults``); ``seed`` overrides the config's seed.

        ``timeline=True`` also runs the config's campaign timeline (``[[events]]``; ``[triggers]``
        without a serial port) as ``faultcam run`` does on a ``files:`` source at ``fps``: frame
        ``k`` has stream time ``k / fps`` and gets the effect states of a sequential run,
        whatever order the indices come in; the record then has an ``events`` list (the
        campaign events logged before the frame).
        """
        return cls(_Chain.from_toml(str(path), seed, timeline, float(fps)))

    @property
    def seed(self) -> int:
        return self._inner.seed

    @property
    def effects(self) -> list[str]:
        """Enabled effects in application (physical) order."""
        return self._inner.effects

    def apply(self, image: np.ndarray, frame_index: int | None = None):
        """Apply the chain to ``image`` as frame ``frame_index`` (default: one more than the last).

        Returns ``(output, record)``: a new array of the same shape and dtype (``None`` when an
        effect such as ``frame_drop`` dropped the frame) and the ground-truth record (dict: seq,
        status, dropped_by, effects with their parameters and generator seeds).
        """
        if frame_index is None:
            frame_index = self._next
        if frame_index < 0:
            raise ValueError(f"frame_index {frame_index} is not accepted; accepted: 0..=2**64-1")
        self._next = frame_index + 1
        if not isinstance(image, np.ndarray):
            raise TypeError(f"image must be a numpy.ndarray, got {type(image).__name__}")
        out, record = self._inner.apply_json(image, int(frame_index))
        return out, json.loads(record)

    def drain(self) -> list:
        """Frames effects still hold at the end of a stream (``reorder``), as ``(output, record)``
        pairs (output ``None`` when a later effect dropped the frame). Call after the last
        ``apply``; every input frame is then accounted for."""
        return [(out, json.loads(rec)) for out, rec in self._inner.drain_json()]

    def __repr__(self) -> str:
        return repr(self._inner)


def effects() -> list[dict]:
    """Every effect: name, stage, summary, model, formats and params (name, unit, min, max,
    default, kind, choices, scale, canonical, range, doc)."""
    return _effects()


try:  # albumentations is optional
    import albumentations as _A
except ImportError:  # pragma: no cover - depends on the environment
    _A = None

if _A is not None:

    class FaultcamTransform(_A.ImageOnlyTransform):
        """albumentations transform applying a faultcam chain.

        Each call takes the next frame index (0, 1, 2, ...), so a dataset pass gets the same
        faults as ``faultcam apply`` on the same images in the same order.
        """

        def __init__(self, config, seed: int | None = None, p: float = 1.0):
            super().__init__(p=p)
            self.config = str(config)
            self.seed = seed
            self.chain = Chain.from_toml(self.config, seed=seed)

        def get_params(self):
            return {"frame_index": self.chain._next}

        def apply(self, img, frame_index: int = 0, **params):
            out, _ = self.chain.apply(np.ascontiguousarray(img), frame_index)
            # A dropped frame has no image: albumentations needs one, keep the input.
            return img if out is None else out

        def get_transform_init_args_names(self):
            return ("config", "seed")

else:

    class FaultcamTransform:  # type: ignore[no-redef]
        """Placeholder: needs albumentations (pip install albumentations)."""

        def __init__(self, *args, **kwargs):
            raise ImportError("faultcam.FaultcamTransform needs albumentations: pip install albumentations")
