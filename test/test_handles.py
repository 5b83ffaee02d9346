"""deepprompt_ros.server.handles: bounded handle store (expiry, LRU eviction, refusal when full),
blended latent distributions (paper Eq. 4). No ROS, no model: fast."""
import threading

import numpy as np
import pytest

from deepprompt_ros.server.handles import (BlendedLatent, ConditionedLatent, HandleLimitError, HandleStore,
                                         Schedule, UnknownHandleError)
from deepprompt_ros.primitive.latent import LatentGaussian


class FakeClock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


def latent(k=4, seed=0):
    rng = np.random.default_rng(seed)
    return LatentGaussian(rng.normal(size=k), rng.uniform(0.1, 2.0, size=k))


def cond(name="reach", seed=0):
    return ConditionedLatent(name, latent(seed=seed))


def test_put_get_returns_the_stored_distribution_under_unique_handles():
    store = HandleStore(max_handles=10, ttl=0)
    values = [cond(seed=i) for i in range(5)]
    handles = [store.put(v, prefix="reach")[0] for v in values]
    assert len(set(handles)) == 5 and all(h.startswith("reach-") for h in handles)
    for h, v in zip(handles, values):
        assert store.get(h) is v
    assert len(store) == 5
    assert store.put(values[0])[1] == 0.0  # ttl 0: never expires


def test_handle_expires_after_ttl_without_use_and_use_refreshes_it():
    clock = FakeClock()
    store = HandleStore(max_handles=10, ttl=60.0, clock=clock)
    h, expires = store.put(cond())
    assert expires == 60.0
    clock.t += 59.0
    store.get(h)  # used: expiry restarts
    assert store.expires_in(h) == pytest.approx(60.0)
    clock.t += 59.0
    assert h in store
    clock.t += 1.5
    assert h not in store
    with pytest.raises(UnknownHandleError, match="expired"):
        store.get(h)


def test_full_store_evicts_the_least_recently_used_handle():
    store = HandleStore(max_handles=3, ttl=0, evict_when_full=True)
    h1, h2, h3 = (store.put(cond(seed=i))[0] for i in range(3))
    store.get(h1)  # h2 is now the least recently used
    h4 = store.put(cond(seed=4))[0]
    assert len(store) == 3
    assert {h1, h3, h4} == {h for h in (h1, h2, h3, h4) if h in store}
    with pytest.raises(UnknownHandleError, match="evicted"):
        store.get(h2)
    assert store.evicted == 1


def test_full_store_refuses_when_eviction_is_disabled():
    store = HandleStore(max_handles=2, ttl=0, evict_when_full=False)
    a = store.put(cond())[0]
    store.put(cond())
    with pytest.raises(HandleLimitError, match="maximum of 2 handles"):
        store.put(cond())
    assert store.remove(a)
    store.put(cond())  # room again
    assert len(store) == 2


def test_unknown_handle_message_says_what_is_expected():
    store = HandleStore()
    with pytest.raises(UnknownHandleError, match="unknown handle 'nope'.*Condition or Blend"):
        store.get("nope")
    long = "x" * 10_000
    with pytest.raises(UnknownHandleError) as info:
        store.get(long)
    assert len(str(info.value)) < 200  # absurd input is not echoed back in full


@pytest.mark.parametrize("kwargs", [dict(max_handles=0), dict(max_handles=2.5), dict(ttl=-1.0),
                                    dict(ttl=float("nan"))])
def test_invalid_store_parameters_are_refused(kwargs):
    with pytest.raises(ValueError):
        HandleStore(**kwargs)


def test_concurrent_use_keeps_the_bound_and_loses_nothing_it_keeps():
    store = HandleStore(max_handles=50, ttl=0)
    errors = []

    def worker(seed):
        try:
            for i in range(200):
                h = store.put(cond(seed=seed))[0]
                try:
                    assert store.get(h).primitive == "reach"
                except UnknownHandleError:
                    pass  # evicted by another thread in between: allowed
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(s,)) for s in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len(store) == 50
    assert store.evicted == 8 * 200 - 50


# ------------------------------------------------------------------------------------------------
# blending (paper Eq. 4)
# ------------------------------------------------------------------------------------------------
def test_blend_endpoints_equal_the_parts_and_midpoint_is_the_product_of_gaussians():
    a, b = cond(seed=1), cond(seed=2)
    bl = BlendedLatent("reach", a, b, Schedule.linear_handover())
    x = np.array([0.0, 0.5, 1.0])
    mean, var = bl.latent_at(x)
    assert mean.shape == var.shape == (3, 4)
    np.testing.assert_allclose(mean[0], a.latent.mean, rtol=1e-12)
    np.testing.assert_allclose(var[0], a.latent.var, rtol=1e-12)
    np.testing.assert_allclose(mean[2], b.latent.mean, rtol=1e-12)
    # ω = 0.5: precision 0.5/σa² + 0.5/σb², mean precision-weighted
    pa, pb = 1 / a.latent.var, 1 / b.latent.var
    np.testing.assert_allclose(var[1], 1 / (0.5 * pa + 0.5 * pb), rtol=1e-12)
    np.testing.assert_allclose(mean[1], (0.5 * pa * a.latent.mean + 0.5 * pb * b.latent.mean) / (0.5 * pa + 0.5 * pb),
                               rtol=1e-12)


def test_schedule_interpolates_linearly_and_is_constant_outside_its_knots():
    s = Schedule([0.2, 0.6], [1.0, 0.0])
    np.testing.assert_allclose(s([0.0, 0.2, 0.4, 0.6, 1.0]), [1.0, 1.0, 0.5, 0.0, 0.0])


def test_nested_blend_of_a_blend_is_a_blend_of_phase_dependent_gaussians():
    a, b, c = cond(seed=1), cond(seed=2), cond(seed=3)
    ab = BlendedLatent("reach", a, b, Schedule([0.0], [0.5]))  # constant ω = 0.5
    abc = BlendedLatent("reach", ab, c, Schedule([0.0], [1.0]))  # all of ab
    x = np.linspace(0, 1, 5)
    np.testing.assert_allclose(abc.latent_at(x)[0], ab.latent_at(x)[0], rtol=1e-12)
    np.testing.assert_allclose(abc.latent_at(x)[1], ab.latent_at(x)[1], rtol=1e-12)


def test_blend_needs_one_primitive_and_a_valid_schedule_and_eps():
    with pytest.raises(ValueError, match="one primitive"):
        BlendedLatent("reach", cond("reach"), cond("wave"), Schedule.linear_handover())
    with pytest.raises(ValueError, match="strictly increasing"):
        Schedule([0.5, 0.5], [1.0, 0.0])
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        Schedule([0.0, 1.2], [1.0, 0.0])
    with pytest.raises(ValueError, match="weights"):
        Schedule([0.0, 1.0], [1.0, -0.1])
    with pytest.raises(ValueError, match="one weight per phase"):
        Schedule([0.0, 1.0], [1.0])
    with pytest.raises(ValueError, match="NaN"):
        Schedule([0.0, float("nan")], [1.0, 0.0])
    with pytest.raises(ValueError, match="eps"):
        BlendedLatent("reach", cond(), cond(), Schedule.linear_handover(), eps=np.zeros(3))
