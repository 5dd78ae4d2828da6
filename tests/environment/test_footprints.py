"""Road-user footprints: peak, standard deviations, elongation along the heading, forward skew, clamped
sum."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from density_planner.environment import FootprintConfig, RoadUserTracks, rasterise_road_users
from density_planner.environment.footprints import footprint_stds, resample_tracks

EXACT = FootprintConfig(coarse_cell=0.0)  # every footprint on the grid itself (no interpolation)
H = 0.1
SHAPE = (1, 601, 601)  # 60 m x 60 m, centre cell (300, 300) at the world origin
ORIGIN = (-30.0, -30.0)


def users(x, y, heading, speed, length=4.0, width=2.0, cls=0):
    n = len(x)
    arr = lambda v: np.asarray(v, dtype=np.float64).reshape(n, 1)  # noqa: E731
    return RoadUserTracks(
        arr(x),
        arr(y),
        arr(heading),
        arr(speed),
        np.full(n, length, float),
        np.full(n, width, float),
        np.full(n, cls, np.int64),
        np.arange(n),
    )


def raster(tracks, config=EXACT, shape=SHAPE):
    return rasterise_road_users(tracks, origin=ORIGIN, cell_size=H, shape=shape, config=config)[0].numpy()


def test_standard_deviations_follow_the_paper():
    tr = users([0.0], [0.0], [0.0], [10.0], length=4.5, width=1.8)
    sf, sb, sw = footprint_stds(tr, FootprintConfig())
    assert sb[0, 0] == pytest.approx(5.5)  # length + 1 m
    assert sf[0, 0] == pytest.approx(5.5 + 0.5 * 10)  # skewed forward by 0.5 s x speed
    assert sw[0, 0] == pytest.approx(0.5 * 1.8 + 0.5)


def test_peak_and_one_sigma_values_along_and_across():
    p = raster(users([0.0], [0.0], [0.0], [0.0]))
    assert p[300, 300] == pytest.approx(1.0)
    # along x: s = 4 + 1 = 5 m = 50 cells; across y: s = 0.5 * 2 + 0.5 = 1.5 m = 15 cells (float32: 1e-6)
    assert p[350, 300] == pytest.approx(math.exp(-0.5), abs=1e-6)
    assert p[250, 300] == pytest.approx(math.exp(-0.5), abs=1e-6)
    assert p[300, 315] == pytest.approx(math.exp(-0.5), abs=1e-6)
    # cut off beyond 3 standard deviations
    assert p[300, 346] == 0.0 and p[300, 344] > 0.0


def test_gaussian_is_elongated_along_the_heading():
    heading = math.radians(30.0)
    p = raster(users([0.0], [0.0], [heading], [0.0])).astype(np.float64)
    xs = ORIGIN[0] + H * np.arange(SHAPE[1])
    x, y = np.meshgrid(xs, xs, indexing="ij")
    w = p / p.sum()
    mx, my = (w * x).sum(), (w * y).sum()
    cov = np.array(
        [
            [(w * (x - mx) ** 2).sum(), (w * (x - mx) * (y - my)).sum()],
            [(w * (x - mx) * (y - my)).sum(), (w * (y - my) ** 2).sum()],
        ]
    )
    vals, vecs = np.linalg.eigh(cov)
    major = vecs[:, 1]
    angle = math.degrees(math.atan2(major[1], major[0])) % 180
    # principal axis = heading (discretisation and truncation: well under 1 degree)
    assert angle == pytest.approx(30.0, abs=1.0)
    # truncation at the same Mahalanobis radius keeps the ratio of standard deviations: 5 / 1.5
    assert math.sqrt(vals[1] / vals[0]) == pytest.approx(5.0 / 1.5, rel=0.03)
    assert abs(mx) < 1e-6 and abs(my) < 1e-6


def test_skewed_forward_along_the_motion():
    p = raster(users([0.0], [0.0], [0.0], [8.0]))
    # ahead s = 5 + 4 = 9 m, behind 5 m
    assert p[390, 300] == pytest.approx(math.exp(-0.5), abs=1e-6)
    assert p[250, 300] == pytest.approx(math.exp(-0.5), abs=1e-6)
    assert p[340, 300] > p[260, 300]
    # a user driving backwards is skewed the other way
    q = raster(users([0.0], [0.0], [0.0], [-8.0]))
    assert q[210, 300] == pytest.approx(math.exp(-0.5), abs=1e-6)
    assert q[260, 300] > q[340, 300]


def test_pedestrians_are_small_and_class_certainty_sets_the_peak():
    cfg = FootprintConfig(coarse_cell=0.0, certainty=(1.0, 1.0, 0.6, 1.0))
    p = raster(users([0.0], [0.0], [0.0], [0.0], length=10.0, width=5.0, cls=2), cfg)
    assert p.max() == pytest.approx(0.6)
    assert p[305, 300] == pytest.approx(0.6 * math.exp(-0.5), abs=1e-6)  # s = 0.5 m whatever the dimensions
    assert p[316, 300] == 0.0


def test_clamped_sum_and_absent_users():
    tr = users([0.0, 0.0, np.nan], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0])
    p = raster(tr)
    assert p.max() == 1.0 and p.min() == 0.0
    assert p[330, 300] == pytest.approx(1.0)  # 2 x exp(-0.5 * 0.36) > 1


def test_coarse_lattice_matches_exact_evaluation():
    tr = users([1.23, -7.0, 12.0], [0.37, 5.0, -9.0], [0.3, 2.0, -1.0], [6.0, 0.0, 12.0])
    exact = raster(tr)
    fast = raster(tr, FootprintConfig())
    # bilinear interpolation on 0.4-m cells: h^2 / (8 s^2) = 1 % of the peak for s = 1.5 m, plus the 1.1 %
    # step of the 3-sigma cutoff smeared over one coarse cell
    assert np.abs(exact - fast).max() < 0.025


def test_raster_threads_give_the_same_grid_to_the_bit():
    """Two threads for the rasteriser (the ``plan`` command's setting: static map, footprints with overlaps, coarse
    lattice, clamp) give the grid of one thread to the bit, for both footprint models, and leave torch's thread
    count as it was; the setting refuses non-integers and negatives."""
    import torch

    from density_planner.environment.footprints import raster_threads, set_raster_threads

    rng = np.random.default_rng(3)
    n = 40
    tr = users(rng.uniform(-25, 25, n), rng.uniform(-25, 25, n), rng.uniform(-3, 3, n), rng.uniform(0, 15, n))
    tr.cls[::3] = 1  # pedestrians and cyclists among the vehicles: footprints on the fine grid too
    static = torch.zeros(SHAPE[1:])
    static[:40] = 1.0
    static[200:260, 100:500] = 0.7
    threads = torch.get_num_threads()
    for cfg in (FootprintConfig(), EXACT, FootprintConfig(model="shape")):
        def grid(cfg=cfg):
            return rasterise_road_users(tr, origin=ORIGIN, cell_size=H, shape=SHAPE, config=cfg,
                                        static=static)

        try:
            torch.set_num_threads(1)
            one = grid()
            set_raster_threads(2)
            assert raster_threads() == 2
            two = grid()
            assert torch.get_num_threads() == 1
        finally:
            set_raster_threads(0)
            torch.set_num_threads(threads)
        assert torch.equal(one, two) and float(one.max()) == 1.0 and 0.0 < float(one[:, 300:].mean()) < 0.5
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="raster threads"):
            set_raster_threads(bad)


def test_static_map_is_added_before_clamping():
    import torch

    static = torch.zeros(SHAPE[1:])
    static[:10] = 1.0
    static[300, 300] = 0.5
    p = rasterise_road_users(
        users([0.0], [0.0], [0.0], [0.0]),
        origin=ORIGIN,
        cell_size=H,
        shape=SHAPE,
        config=EXACT,
        static=static,
    )[0]
    assert float(p[:10].min()) == 1.0 and float(p[300, 300]) == 1.0


def test_resample_tracks_interpolates_exactly():
    src = np.arange(5) / 25.0  # 25 Hz
    values = {
        "x": np.array([[0.0, 1.0, 2.0, 3.0, 4.0]]),
        "h": np.array([[math.radians(170), math.radians(179), math.radians(-179), np.nan, 0.0]]),
    }
    out = resample_tracks(values, src, np.array([0.0, 0.1, 0.06, 0.15, 0.2]), angles=("h",))
    assert out["x"][0, :4] == pytest.approx([0.0, 2.5, 1.5, 3.75])
    assert np.isnan(out["x"][0, 4])  # beyond the last sample (frame 5 of 0..4)
    # 179 deg -> -179 deg passes through 180 deg, not through 0
    assert math.cos(out["h"][0, 2]) == pytest.approx(-1.0, abs=1e-12)
    # a NaN neighbour makes the user absent
    assert np.isnan(resample_tracks(values, src, np.array([0.13]), angles=("h",))["h"]).all()


# ------------------------------------------------------------------ shape model (CommonRoad default)
SHAPE_MODEL = FootprintConfig(model="shape", coarse_cell=0.0)


def _rectangle_chance(u, w, length, width, s_u, s_w):
    """Closed form: P(point (u, w) in the rectangle) when the rectangle's centre has N(0, s^2) errors per axis."""
    phi = lambda z: 0.5 * (1.0 + math.erf(z / math.sqrt(2.0)))  # noqa: E731
    return (phi((length / 2 - u) / s_u) - phi((-length / 2 - u) / s_u)) * (
        phi((width / 2 - w) / s_w) - phi((-width / 2 - w) / s_w))


@pytest.mark.parametrize("heading_deg", [0.0, 30.0, -120.0])
def test_shape_model_is_the_chance_that_the_rectangle_covers_a_point(heading_deg):
    th = math.radians(heading_deg)
    p = raster(users([1.0], [-2.0], [th], [15.0], length=4.5, width=1.8), SHAPE_MODEL).astype(np.float64)
    rng = np.random.default_rng(0)
    points = [(0.0, 0.0), (2.25, 0.0), (0.0, 0.9), (2.5, 0.6), (-2.0, -1.0), (3.0, 0.0), *rng.uniform(-3, 3, (6, 2))]
    for u, w in points:
        # the cell nearest to the point (u, w) of the road user's frame; the value is checked at the cell centre
        x, y = 1.0 + u * math.cos(th) - w * math.sin(th), -2.0 + u * math.sin(th) + w * math.cos(th)
        i, j = int(round((x - ORIGIN[0]) / H)), int(round((y - ORIGIN[1]) / H))
        xc, yc = ORIGIN[0] + i * H - 1.0, ORIGIN[1] + j * H + 2.0
        uc, wc = xc * math.cos(th) + yc * math.sin(th), -xc * math.sin(th) + yc * math.cos(th)
        expected = _rectangle_chance(uc, wc, 4.5, 1.8, 0.2, 0.2)
        assert p[i, j] == pytest.approx(expected if expected > 2e-3 else p[i, j], abs=2e-5)
    # no skew along the motion (speed 15 m/s), and nothing beyond 3 stds outside the rectangle
    i = int(round((1.0 + 3.0 * math.cos(th) - ORIGIN[0]) / H))
    j = int(round((-2.0 + 3.0 * math.sin(th) - ORIGIN[1]) / H))
    assert p[i, j] == 0.0


def test_shape_model_spreads_with_the_prediction_error():
    """Past the last recorded state the position error grows (rates 1 and 0.3 m/s): after 5 s the centre value is
    the closed form with stds sqrt(0.2^2 + 5^2) along and sqrt(0.2^2 + 1.5^2) across."""
    tr = users([0.0], [0.0], [0.0], [0.0])
    tr = RoadUserTracks(tr.x, tr.y, tr.heading, tr.speed, tr.length, tr.width, tr.cls, tr.ids,
                        predicted_for=np.array([[5.0]]))
    p = raster(tr, SHAPE_MODEL)
    expected = _rectangle_chance(0.0, 0.0, 4.0, 2.0, math.hypot(0.2, 5.0), math.hypot(0.2, 1.5))
    assert p[300, 300] == pytest.approx(expected, abs=1e-5)
    assert p[300, 300] < 0.5


def test_shape_model_on_the_coarse_lattice_matches_the_exact_one():
    tr = users([0.3], [0.1], [0.4], [0.0])
    tr = RoadUserTracks(tr.x, tr.y, tr.heading, tr.speed, tr.length, tr.width, tr.cls, tr.ids,
                        predicted_for=np.array([[3.0]]))  # stds >= 1.2 m: the coarse lattice is used
    exact = raster(tr, SHAPE_MODEL)
    coarse = raster(tr, FootprintConfig(model="shape"))
    assert np.abs(exact - coarse).max() < 0.02


def test_footprint_model_is_checked():
    with pytest.raises(ValueError, match="FootprintConfig.model must be one of gaussian, shape"):
        FootprintConfig(model="box")
    with pytest.raises(ValueError, match="shape_std"):
        FootprintConfig(shape_std=0.0)


def test_prediction_error_grows_with_velocity_and_acceleration_terms():
    """``e = hypot(rate tau, accel tau^2 / 2)`` per axis; without accelerations the linear growth alone (the
    defaults), and the predicted footprint's standard deviations are the recorded ones convolved with it."""
    from density_planner.environment.footprints import prediction_errors

    tau = np.array([0.0, 1.0, 2.0, 5.0])
    e_u, e_w = prediction_errors(tau, FootprintConfig())
    np.testing.assert_allclose(e_u, 1.0 * tau)
    np.testing.assert_allclose(e_w, 0.3 * tau)
    cfg = FootprintConfig(prediction_accel_std_along=0.6, prediction_accel_std_across=0.4)
    e_u, e_w = prediction_errors(tau, cfg)
    np.testing.assert_allclose(e_u, np.sqrt((1.0 * tau) ** 2 + (0.3 * tau**2) ** 2))
    np.testing.assert_allclose(e_w, np.sqrt((0.3 * tau) ** 2 + (0.2 * tau**2) ** 2))
    assert e_u[-1] == pytest.approx(math.hypot(5.0, 7.5)) and e_w[-1] == pytest.approx(math.hypot(1.5, 5.0))
    one = np.ones((1, 4))
    tracks = RoadUserTracks(np.zeros((1, 4)), np.zeros((1, 4)), np.zeros((1, 4)), 10.0 * one, np.array([4.5]),
                            np.array([1.8]), np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64))
    s_front0, _, s_w0 = footprint_stds(tracks, cfg)
    predicted = RoadUserTracks(tracks.x, tracks.y, tracks.heading, tracks.speed, tracks.length, tracks.width,
                               tracks.cls, tracks.ids, tau[None, :])
    s_front, _, s_w = footprint_stds(predicted, cfg)
    np.testing.assert_allclose(s_front, np.hypot(s_front0, e_u[None, :]))
    np.testing.assert_allclose(s_w, np.hypot(s_w0, e_w[None, :]))
    with pytest.raises(ValueError, match="prediction_accel_std_along"):
        FootprintConfig(prediction_accel_std_along=-1.0)


@pytest.mark.parametrize("model", ["gaussian", "shape"])
def test_a_row_weight_scales_its_footprint(model):
    tr = users([0.0, 0.0], [-15.0, 15.0], [0.0, 0.0], [5.0, 5.0])  # side by side, 30 m apart across
    cfg = dataclasses.replace(EXACT, model=model)
    full = raster(tr, cfg)
    half = raster(dataclasses.replace(tr, weight=np.array([0.5, 1.0])), cfg)
    left, right = (slice(None), slice(0, 300)), (slice(None), slice(300, None))  # y < 0: the first user's cells
    assert full[left].max() > 0.5 and full[right].max() > 0.5
    np.testing.assert_allclose(half[left], 0.5 * full[left], atol=1e-6)
    np.testing.assert_allclose(half[right], full[right], atol=1e-6)


@pytest.mark.parametrize("weight", [np.array([0.5]), np.array([0.5, 1.5]), np.array([-0.1, 1.0]),
                                    np.array([np.nan, 1.0])])
def test_row_weights_must_be_probabilities_one_per_row(weight):
    tr = users([0.0, 8.0], [0.0, 0.0], [0.0, 0.0], [5.0, 5.0])
    with pytest.raises(ValueError, match="weight"):
        dataclasses.replace(tr, weight=weight)


@pytest.mark.parametrize("factor, shape", [(2, (57, 80)), (3, (60, 79)), (4, (61, 81)), (3, (58, 77))])
def test_upsample_active_equals_the_whole_interpolation(factor, shape):
    from density_planner.environment.footprints import upsample_active

    gen = torch.Generator().manual_seed(factor)
    ncx, ncy = (shape[0] - 1 + factor - 1) // factor + 1, (shape[1] - 1 + factor - 1) // factor + 1
    low = torch.zeros(7, ncx, ncy)
    # a few sparse blobs that move between slices, one on the lattice's last row and column, one slice empty
    for k in range(6):
        i, j = int(torch.randint(0, ncx - 3, (1,), generator=gen)), int(torch.randint(0, ncy - 3, (1,), generator=gen))
        low[k, i:i + 3, j:j + 2] = torch.rand(3, 2, generator=gen)
    low[2, -1, -1] = 0.7
    low[4, 0, -2:] = 0.3
    whole = torch.nn.functional.interpolate(low[None], size=((ncx - 1) * factor + 1, (ncy - 1) * factor + 1),
                                            mode="bilinear", align_corners=True)[0][:, : shape[0], : shape[1]]
    base = torch.rand(7, *shape, generator=gen)
    for tile in (1, 4, 16):
        got = upsample_active(low, factor, base.clone(), tile=tile)  # added in place
        torch.testing.assert_close(got, base + whole, atol=2e-6, rtol=0)  # float rounding of the weights (1/3)
        assert bool((got[6] == base[6]).all()) and bool((got[whole == 0] == base[whole == 0]).all())
    assert bool((upsample_active(torch.zeros(3, ncx, ncy), factor, torch.zeros(3, *shape)) == 0).all())


def test_non_finite_inputs_of_the_rasteriser_are_refused(monkeypatch):
    """Its grid's values are finite by construction (no check of the cells follows): a NaN in the static map or in
    a present user's footprint parameters is refused, naming it."""
    import torch

    from density_planner.environment import footprints

    static = torch.zeros(SHAPE[1:])
    static[5, 5] = float("nan")
    with pytest.raises(ValueError, match="static occupancy map holds NaN"):
        rasterise_road_users(users([0.0], [0.0], [0.0], [0.0]), origin=ORIGIN, cell_size=H, shape=SHAPE,
                             config=EXACT, static=static)
    real = footprints.footprint_stds
    monkeypatch.setattr(footprints, "footprint_stds",
                        lambda tracks, cfg: tuple(np.where(tracks.x > 5.0, np.nan, s) for s in real(tracks, cfg)))
    with pytest.raises(ValueError, match="road user 1: a non-finite footprint parameter"):
        raster(users([0.0, 10.0], [0.0, 0.0], [0.0, 0.0], [1.0, 1.0]))
