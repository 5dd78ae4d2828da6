"""Training data of the learned density predictors: shapes, determinism per seed, batching, resuming, split."""

from __future__ import annotations

import json

import pytest
import torch
from density_testdata import TINY

from density_planner.config import update
from density_planner.control.analytic import CarTrackingController
from density_planner.control.reference import make_reference
from density_planner.density.data import (
    SHARD_KEYS,
    DensityDataConfig,
    generate_density_data,
    generate_shard,
    load_density_data,
)
from density_planner.density.liouville import propagate_density
from density_planner.errors import DataError
from density_planner.systems.car import BIAS, KinematicCar


def test_shard_shapes_and_invariants():
    data = generate_shard(TINY, 0)
    b, n, t = TINY.references_per_shard, TINY.samples, 101
    shapes = {"xe0": (b, n, 5), "ref_start": (b, 5), "params": (b, 2, 10), "t": (t,), "xe": (b, n, t, 5),
              "log_ratio": (b, n, t), "x_ref": (b, t, 5)}
    assert set(SHARD_KEYS) == set(shapes)
    for k, shape in shapes.items():
        assert tuple(data[k].shape) == shape, k
        assert data[k].dtype == torch.float32
        assert data[k].untyped_storage().nbytes() == data[k].numel() * 4, k  # no views of larger tensors on disk
    # exact structure: the error starts at xe0, the log-density ratio at 0, the bias error is constant
    torch.testing.assert_close(data["xe"][:, :, 0], data["xe0"], rtol=0, atol=1e-6)
    assert float(data["log_ratio"][..., 0].abs().max()) == 0.0
    torch.testing.assert_close(data["xe"][..., BIAS], data["xe0"][..., BIAS, None].expand(b, n, t))
    # initial errors inside error_scale * XE0, parameters inside the input bounds, reference from its parameters
    half = torch.tensor(KinematicCar().config.initial_error_max) * TINY.error_scale
    assert bool((data["xe0"].abs() <= half + 1e-6).all())
    assert float(data["params"].abs().max()) <= 3.0
    ref = make_reference(KinematicCar(), data["ref_start"], data["params"])
    torch.testing.assert_close(ref.x_plan, data["x_ref"])
    assert torch.allclose(data["t"], torch.arange(t) * 0.1)


def test_shard_determinism_per_seed():
    a, b = generate_shard(TINY, 1), generate_shard(TINY, 1)
    for k in SHARD_KEYS:
        assert torch.equal(a[k], b[k]), k
    other = generate_shard(update(TINY, {"seed": TINY.seed + 1}), 1)
    assert not torch.equal(a["xe0"], other["xe0"])
    assert not torch.equal(a["params"], generate_shard(TINY, 2)["params"])  # shards are independent streams


def test_batched_shard_equals_single_reference_propagation():
    """A shard is propagated batched over its references; each reference alone gives the same trajectories."""
    data = generate_shard(TINY, 0)
    car, ctrl = KinematicCar(), CarTrackingController()
    for i in range(TINY.references_per_shard):
        ref = make_reference(car, data["ref_start"][i], data["params"][i])
        with torch.no_grad():
            out = propagate_density(car, ctrl, ref.start + data["xe0"][i], ref)
        # float32 results of a batched vs an unbatched evaluation differ by round-off only
        torch.testing.assert_close(out.x - ref.x_plan.unsqueeze(-3), data["xe"][i], rtol=0, atol=1e-4)
        torch.testing.assert_close(out.log_rho, data["log_ratio"][i], rtol=0, atol=1e-3)


def test_generate_manifest_split_and_load(tiny_data):
    manifest = json.loads((tiny_data / "manifest.json").read_text())
    assert manifest["complete"] is True
    assert manifest["sizes"]["references_train"] == 6 and manifest["sizes"]["references_val"] == 2
    assert [s["split"] for s in manifest["shards"]] == ["train", "train", "train", "val"]
    assert manifest["controller_fingerprint"]
    train, val = load_density_data(tiny_data, "train"), load_density_data(tiny_data, "val")
    assert len(train) == 6 * TINY.samples and len(val) == 2 * TINY.samples
    assert train.n_references == 6 and val.n_references == 2
    # the split is by reference: no reference appears in both
    assert not set(train.reference_id.tolist()) & set(val.reference_id.tolist())
    assert train.xe.shape == (len(train), 101, 5) and train.x_ref_heading.shape == (len(train), 101)
    # rows of one reference share its parameters
    rows = train.reference_id == train.reference_id[0]
    assert torch.equal(train.params[rows], train.params[0].expand(int(rows.sum()), 2, 10))
    shard = generate_shard(TINY, 0)
    torch.testing.assert_close(train.xe[: TINY.samples], shard["xe"][0])


def test_generation_is_resumable(tmp_path):
    out = tmp_path / "d"
    generate_density_data(TINY, out, workers=1)
    files = sorted(out.glob("shard_*.pt"))
    before = {f.name: f.read_bytes() for f in files}
    mtimes = {f.name: f.stat().st_mtime_ns for f in files}
    files[1].unlink()  # a missing shard
    files[2].write_bytes(b"not a torch file")  # a corrupt shard (e.g. from a foreign tool)
    done = []
    generate_density_data(TINY, out, workers=1, on_shard=done.append)
    assert sorted(d["index"] for d in done) == [1, 2]  # only those two were generated again
    assert files[0].stat().st_mtime_ns == mtimes[files[0].name]
    assert (out / "shard_00000.pt").read_bytes() == before["shard_00000.pt"]
    for i in (1, 2):  # the regenerated shards equal a fresh generation (deterministic per (seed, shard))
        a = torch.load(out / f"shard_{i:05d}.pt", weights_only=True)
        assert torch.equal(a["xe"], generate_shard(TINY, i)["xe"])
    assert not list(out.glob(".*.tmp"))  # atomic writes leave no temporary files


def test_generation_parallel_matches_serial(tmp_path):
    generate_density_data(TINY, tmp_path / "serial", workers=1)
    generate_density_data(TINY, tmp_path / "par", workers=2)
    for i in range(TINY.n_shards):
        a = torch.load(tmp_path / "serial" / f"shard_{i:05d}.pt", weights_only=True)
        b = torch.load(tmp_path / "par" / f"shard_{i:05d}.pt", weights_only=True)
        assert torch.equal(a["xe"], b["xe"]) and torch.equal(a["log_ratio"], b["log_ratio"])


def test_other_configuration_in_same_directory_is_refused(tiny_data, tmp_path):
    out = tmp_path / "d"
    generate_density_data(TINY, out, workers=1)
    with pytest.raises(DataError, match="another configuration"):
        generate_density_data(update(TINY, {"samples": 3}), out, workers=1)


def test_load_errors(tmp_path):
    with pytest.raises(DataError, match="not a density data directory"):
        load_density_data(tmp_path)
    out = tmp_path / "d"
    generate_density_data(TINY, out, workers=1)
    with pytest.raises(ValueError, match="split"):
        load_density_data(out, "test")
    (out / "shard_00003.pt").write_bytes(b"garbage")
    with pytest.raises(DataError, match="corrupt"):
        load_density_data(out, "val")
    manifest = json.loads((out / "manifest.json").read_text())
    manifest["complete"] = False
    (out / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DataError, match="incomplete"):
        load_density_data(out, "train")


def test_config_validation():
    with pytest.raises(ValueError, match="references"):
        DensityDataConfig(references=0)
    with pytest.raises(ValueError, match="validation"):
        DensityDataConfig(references=4, references_per_shard=4)  # one shard cannot be split
    with pytest.raises(ValueError, match="start_low"):
        DensityDataConfig(start_low=(0.0, 0.0))
    with pytest.raises(ValueError, match="out of range"):
        generate_shard(TINY, TINY.n_shards)
    assert DensityDataConfig(references=10, references_per_shard=4).n_shards == 3
