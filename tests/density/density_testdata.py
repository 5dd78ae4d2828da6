"""Small synthetic density data sets for the tests (analytic controller, a few references)."""

from __future__ import annotations

from pathlib import Path

from density_planner.density.data import DensityDataConfig, generate_density_data

#: 8 references x 6 samples in 4 shards (the last one is the validation split); about 1 s to generate
TINY = DensityDataConfig(references=8, samples=6, references_per_shard=2, validation_fraction=0.25, seed=3,
                         controller="analytic")
#: enough data for a few epochs to lower the validation loss: 160 references x 4 samples (many references: the
#: reference features need them), gentle references (parameters 0.5 N(0, 1): the analytic controller rarely
#: saturates, so the data has no heavy tails)
SMALL = DensityDataConfig(references=160, samples=4, references_per_shard=20, validation_fraction=0.25, seed=5,
                          controller="analytic", param_scale=0.5)


def make_data(tmp: Path, config: DensityDataConfig = TINY) -> Path:
    out = tmp / "data"
    generate_density_data(config, out, workers=1)
    return out
