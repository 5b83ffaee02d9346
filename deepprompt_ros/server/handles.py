"""Conditioned latent distributions stored under string handles (ROS-free).

A client conditions a primitive once (``Condition`` service), gets a handle, and then refers to
the stored distribution by that handle (``Execute``, ``Blend``, ``Sample``). This module holds:

* :class:`ConditionedLatent` -- q(z) = N(μ, diag σ²) of one primitive (paper Eq. 1), constant in
  the phase;
* :class:`BlendedLatent` -- q_b(z | x) ∝ q_a(z | x)^ω(x) q_b(z | x)^(1 - ω(x)) (paper Eq. 4), a
  phase-dependent Gaussian built from two stored distributions and a schedule ω(x); blends can
  be nested. With ``eps`` set, the trajectory it stands for is z(x) = μ_b(x) + ε σ_b(x) with ONE
  ε for the whole trajectory (the motion stays smooth);
* :class:`HandleStore` -- a bounded, thread-safe store with expiry (a handle unused for
  ``ttl`` seconds is dropped; every use refreshes it) and least-recently-used eviction when full
  (or a refusal, :class:`HandleLimitError`, when eviction is disabled).

Every distribution answers ``latent_at(x) -> (mean (T, k), var (T, k))``, so decoding a handle is
the same code path for conditioned and blended handles
(:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.decode_per_phase`).
"""
from __future__ import annotations

import collections
import dataclasses
import itertools
import math
import secrets
import threading
import time
from typing import TYPE_CHECKING, Callable, Union

import numpy as np

from deepprompt_ros.primitive.blending import blend_gaussians, blend_mode_weights

if TYPE_CHECKING:  # torch-free import (the server validates its parameters before loading torch)
    from deepprompt_ros.primitive.latent import LatentGaussian

__all__ = [
    "ConditionedLatent",
    "BlendedLatent",
    "StoredDistribution",
    "Schedule",
    "HandleError",
    "UnknownHandleError",
    "HandleLimitError",
    "HandleStore",
]


@dataclasses.dataclass(frozen=True)
class Schedule:
    """Blending schedule ω(x): weight of the first distribution at the phases of the knots,
    linear interpolation between them, constant before the first and after the last knot.

    Attributes
    ----------
    phases : array, shape (m,)
        Strictly increasing, in [0, 1]; m >= 1.
    weights : array, shape (m,)
        In [0, 1].
    """

    phases: np.ndarray
    weights: np.ndarray

    def __post_init__(self):
        x = np.array(self.phases, dtype=np.float64).reshape(-1)
        w = np.array(self.weights, dtype=np.float64).reshape(-1)
        if x.shape != w.shape:
            raise ValueError(f"blending schedule has {x.size} phases and {w.size} weights; "
                             "expected one weight per phase")
        if x.size == 0:
            raise ValueError("blending schedule needs at least one (phase, weight) knot")
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(w))):
            raise ValueError("blending schedule contains NaN or inf; expected finite phases and weights")
        if x.min() < 0 or x.max() > 1:
            raise ValueError(f"schedule phases must lie in [0, 1]; got {x.tolist()}")
        if np.any(np.diff(x) <= 0):
            raise ValueError(f"schedule phases must be strictly increasing; got {x.tolist()}")
        if w.min() < 0 or w.max() > 1:
            raise ValueError(f"schedule weights ω must lie in [0, 1]; got {w.tolist()}")
        x.setflags(write=False)
        w.setflags(write=False)
        object.__setattr__(self, "phases", x)
        object.__setattr__(self, "weights", w)

    @classmethod
    def linear_handover(cls) -> "Schedule":
        """ω(0) = 1 (all of the first), ω(1) = 0 (all of the second), linear in between."""
        return cls(np.array([0.0, 1.0]), np.array([1.0, 0.0]))

    def __call__(self, x) -> np.ndarray:
        """ω at phases x, array shape (T,) -> (T,)."""
        return np.interp(np.asarray(x, dtype=np.float64), self.phases, self.weights)


@dataclasses.dataclass(frozen=True)
class ConditionedLatent:
    """q(z | via-points, contexts) of primitive ``primitive`` (constant over the phase).

    Attributes
    ----------
    primitive : str
    latent : LatentGaussian, mean/var shape (k,)
    """

    primitive: str
    latent: LatentGaussian

    @property
    def parts(self) -> int:
        """One conditioned distribution."""
        return 1

    @property
    def eps(self) -> None:
        """Conditioned handles follow their mean (ε = 0)."""
        return None

    @property
    def latent_dim(self) -> int:
        return int(np.shape(self.latent.mean)[0])

    def latent_at(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance at phases x (T,): each shape (T, k), the same row repeated."""
        n = np.shape(x)[0]
        return (np.broadcast_to(self.latent.mean, (n, self.latent_dim)),
                np.broadcast_to(self.latent.var, (n, self.latent_dim)))

    def mode_weights_at(self, x, mode_weights) -> np.ndarray:
        """The weights of the decoder's modes at phases x (T,), (T, K): ``mode_weights(latent)`` (K,) of
        this latent on every row (:meth:`deepprompt_ros.primitive.deep_promp.DeepProMP.mode_weights`)."""
        w = mode_weights(self.latent)
        return np.broadcast_to(w, (np.shape(x)[0], w.shape[0]))


@dataclasses.dataclass(frozen=True)
class BlendedLatent:
    """q_b(z | x) ∝ a(z | x)^ω(x) · b(z | x)^(1 - ω(x)), per latent dimension (paper Eq. 4).

    Attributes
    ----------
    primitive : str
        Both parts belong to this primitive (one decoder, one latent space).
    a, b : ConditionedLatent or BlendedLatent
    schedule : Schedule
        ω(x), the weight of ``a``.
    eps : array, shape (k,), or None
        The ONE noise draw of the trajectory, z(x) = μ_b(x) + ε σ_b(x); None follows μ_b(x).
    parts : int
        The conditioned distributions it is made of, counted with repeats (``a.parts + b.parts``):
        :meth:`latent_at` evaluates each of them, so its time grows with this number.
    """

    primitive: str
    a: "StoredDistribution"
    b: "StoredDistribution"
    schedule: Schedule
    eps: np.ndarray | None = None
    parts: int = dataclasses.field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "parts", self.a.parts + self.b.parts)
        for part in (self.a, self.b):
            if part.primitive != self.primitive:
                raise ValueError(f"blending needs both distributions of one primitive; got "
                                 f"'{self.a.primitive}' and '{self.b.primitive}'")
        if self.a.latent_dim != self.b.latent_dim:
            raise ValueError("blended distributions have different latent dimensions")
        if self.eps is not None:
            eps = np.array(self.eps, dtype=np.float64).reshape(-1)
            if eps.shape != (self.a.latent_dim,) or not np.all(np.isfinite(eps)):
                raise ValueError(f"eps must be {self.a.latent_dim} finite values")
            eps.setflags(write=False)
            object.__setattr__(self, "eps", eps)

    @property
    def latent_dim(self) -> int:
        return self.a.latent_dim

    def latent_at(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Mean and variance of q_b(z | x) at phases x (T,): each shape (T, k).

        Product of the two Gaussians raised to ω and 1 - ω
        (:func:`deepprompt_ros.primitive.blending.blend_gaussians`).
        """
        x = np.asarray(x, dtype=np.float64)
        ma, va = self.a.latent_at(x)
        mb, vb = self.b.latent_at(x)
        return blend_gaussians(self.schedule(x), ma, va, mb, vb)

    def mode_weights_at(self, x, mode_weights) -> np.ndarray:
        """The weights of the decoder's modes at phases x (T,), (T, K): a's and b's blended by ω(x)
        (:func:`deepprompt_ros.primitive.blending.blend_mode_weights`)."""
        x = np.asarray(x, dtype=np.float64)
        return blend_mode_weights(self.schedule(x), self.a.mode_weights_at(x, mode_weights),
                                  self.b.mode_weights_at(x, mode_weights))


StoredDistribution = Union[ConditionedLatent, BlendedLatent]


class HandleError(LookupError):
    """Base class of the store's errors; ``str(exc)`` says what is wrong and what to do."""


class UnknownHandleError(HandleError):
    """The handle was never issued, has expired, or was evicted."""


class HandleLimitError(HandleError):
    """The store is full and eviction is disabled."""


class _Entry:
    __slots__ = ("value", "last_used")

    def __init__(self, value, last_used: float):
        self.value = value
        self.last_used = last_used


class HandleStore:
    """Bounded, thread-safe map handle -> stored distribution with expiry and LRU eviction.

    Parameters
    ----------
    max_handles : int
        Capacity, >= 1.
    ttl : float
        Seconds after its last use at which a handle expires; 0 = never.
    evict_when_full : bool
        Full store: True drops the least recently used handle to make room; False refuses
        (:class:`HandleLimitError`).
    clock : callable () -> float
        Monotonic time in seconds (injectable for tests).
    """

    def __init__(self, max_handles: int = 64, ttl: float = 600.0, evict_when_full: bool = True,
                 clock: Callable[[], float] = time.monotonic):
        if int(max_handles) != max_handles or max_handles < 1:
            raise ValueError(f"max_handles must be an integer >= 1; got {max_handles}")
        if not (math.isfinite(ttl) and ttl >= 0):
            raise ValueError(f"ttl must be a finite number of seconds >= 0 (0 = never expires); got {ttl}")
        self.max_handles = int(max_handles)
        self.ttl = float(ttl)
        self.evict_when_full = bool(evict_when_full)
        self._clock = clock
        self._lock = threading.Lock()
        self._entries: collections.OrderedDict[str, _Entry] = collections.OrderedDict()  # LRU first
        self._counter = itertools.count(1)
        self._expired: collections.OrderedDict[str, None] = collections.OrderedDict()  # recent, for messages
        self.evicted = 0

    # ---------------------------------------------------------------- internals
    def _purge(self, now: float) -> None:
        if self.ttl <= 0:
            return
        while self._entries:
            handle, entry = next(iter(self._entries.items()))
            if now - entry.last_used < self.ttl:
                break
            del self._entries[handle]
            self._remember_gone(handle, "expired")

    def _remember_gone(self, handle: str, why: str) -> None:
        self._expired[handle] = why
        while len(self._expired) > 4 * self.max_handles:
            self._expired.popitem(last=False)

    # ---------------------------------------------------------------- API
    def put(self, value: StoredDistribution, prefix: str = "h") -> tuple[str, float]:
        """Store ``value`` under a new handle.

        Returns
        -------
        handle : str
            ``<prefix>-<serial>-<random hex>``; never reused.
        expires_in : float
            Seconds until it expires if unused (0 = never).

        Raises
        ------
        HandleLimitError
            The store is full and ``evict_when_full`` is False.
        """
        with self._lock:
            now = self._clock()
            self._purge(now)
            if len(self._entries) >= self.max_handles:
                if not self.evict_when_full:
                    raise HandleLimitError(
                        f"the server holds its maximum of {self.max_handles} handles; wait until "
                        f"unused handles expire (after {self.ttl:g} s) or raise the parameter max_handles")
                old, _ = self._entries.popitem(last=False)
                self._remember_gone(old, "evicted (least recently used, store full)")
                self.evicted += 1
            safe = "".join(c if c.isalnum() or c in "_-" else "_" for c in prefix)[:32] or "h"
            handle = f"{safe}-{next(self._counter)}-{secrets.token_hex(3)}"
            self._entries[handle] = _Entry(value, now)
            return handle, self.ttl

    def get(self, handle: str) -> StoredDistribution:
        """The distribution under ``handle``; refreshes its expiry and LRU position.

        Raises
        ------
        UnknownHandleError
            With the reason (never issued / expired / evicted).
        """
        with self._lock:
            now = self._clock()
            self._purge(now)
            entry = self._entries.get(handle)
            if entry is None:
                why = self._expired.get(handle)
                if why is not None:
                    raise UnknownHandleError(f"handle '{handle}' was {why}; call Condition again "
                                             f"(handles expire {self.ttl:g} s after their last use)"
                                             if why == "expired" else
                                             f"handle '{handle}' was {why}; call Condition again or "
                                             f"raise the parameter max_handles ({self.max_handles})")
                shown = handle if len(handle) <= 64 else handle[:64] + "..."
                raise UnknownHandleError(f"unknown handle '{shown}'; expected a handle returned by "
                                         "Condition or Blend")
            entry.last_used = now
            self._entries.move_to_end(handle)
            return entry.value

    def expires_in(self, handle: str) -> float:
        """Seconds until ``handle`` expires if unused (0 = never); raises UnknownHandleError."""
        with self._lock:
            entry = self._entries.get(handle)
            if entry is None:
                raise UnknownHandleError(f"unknown handle '{handle}'")
            if self.ttl <= 0:
                return 0.0
            return max(self.ttl - (self._clock() - entry.last_used), 0.0)

    def remove(self, handle: str) -> bool:
        """Drop a handle; True if it existed."""
        with self._lock:
            if self._entries.pop(handle, None) is None:
                return False
            self._remember_gone(handle, "removed")
            return True

    def __len__(self) -> int:
        with self._lock:
            self._purge(self._clock())
            return len(self._entries)

    def __contains__(self, handle: str) -> bool:
        with self._lock:
            self._purge(self._clock())
            return handle in self._entries
