"""Exact Liouville on the road domain: stop 53's speed-step schedule (RK4 at the step of each band of the references'
top speed) against the error-controlled dopri5, per band, on 100 random road references x 20 samples of a seed,
against float64 RK4 at 0.005 s; largest log-density error and wall time (float32, one thread, inference mode; the
table in docs/core.md, "An error-controlled integrator").

    python benchmarks/compare_liouville_schemes.py SEED TOLERANCE
"""
import copy, sys, time, torch
torch.set_num_threads(1)
from density_planner.control.registry import model_set, load_controller
from density_planner.control.sampling import sample_feasible_references, sample_initial_errors
from density_planner.density.liouville import LiouvilleConfig, propagate_density
system = model_set("road").make_system(); controller = load_controller(None, models="road")
seed = int(sys.argv[1]); tol = float(sys.argv[2])
gen = torch.Generator().manual_seed(seed)
ref64 = sample_feasible_references(system, 100, gen, dtype=torch.float64)
xe0 = sample_initial_errors(2000, gen, box=system.config.initial_error_max, dtype=torch.float64).reshape(100, 20, 5)
x0 = ref64.start.unsqueeze(-2) + xe0
top = ref64.x[..., 3].abs().amax(-1)
fine = propagate_density(system, copy.deepcopy(controller).double(), x0, ref64, config=LiouvilleConfig("rk4", 0.005)).log_rho
r32 = type(ref64)(ref64.params.float(), ref64.x.float(), ref64.u.float(), ref64.parameterization)
c32 = copy.deepcopy(controller).float()
def run(sel, cfg):
    t0 = time.perf_counter()
    with torch.inference_mode():
        o = propagate_density(system, c32, x0.float()[sel], r32.select(sel), config=cfg)
    return time.perf_counter() - t0, float((o.log_rho.double() - fine[sel]).abs().max())
res = {}
for lo, hi, step in ((0, 15, 0.1), (15, 20, 0.05), (20, 25, 0.025), (25, 45, 0.02)):
    sel = torch.nonzero((top >= lo) & (top < hi)).squeeze(-1)
    if not len(sel): continue
    ws, es = run(sel, LiouvilleConfig("rk4", step))
    wd, ed = run(sel, LiouvilleConfig("dopri5", tolerance=tol))
    print(f"seed {seed} [{lo},{hi}) n={len(sel)}: schedule rk4 {step}: {es:.3f} nats {ws:.2f} s | dopri5 {tol:g}: {ed:.3f} nats {wd:.2f} s", flush=True)
