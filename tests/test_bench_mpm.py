"""`cosim bench mpm --sizes`: the grid grows with the block so that it keeps 8 particles per cell
(2 per axis) and fills the same share of the domain, at every size of the sweep."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.bench.mpm import FILL, SIZES, sized_grid
from cosim.bench.mpm_measure import block_points


def test_sized_grid_keeps_8_particles_per_cell():
    for particles, _, _ in SIZES:
        cfg = sized_grid(particles)
        pts = block_points(3, cfg["cells"], cfg["side"])
        assert abs(len(pts) / particles - 1) < 0.1, cfg  # the size asked for, within 10%
        cell = np.floor(pts * cfg["cells"]).astype(np.int64) @ cfg["cells"] ** np.arange(3)  # flat cell index
        counts = np.bincount(cell)
        assert abs(np.median(counts[counts > 0]) / 8 - 1) < 0.1, cfg  # a cell inside holds 2 x 2 x 2
        span = np.ptp(pts, axis=0).max() + 0.5 / cfg["cells"]  # [m] the block's side; the domain's is 1
        assert abs(span / FILL - 1) < 0.1, cfg  # the same share of the domain at every size


def test_the_gpu_sizes_are_30k_250k_and_2m_particles():
    from cosim.bench.mpm import GPU_CONFIGS

    counts = [len(block_points(3, c["cells"], c["side"])) for c in GPU_CONFIGS]
    for got, want in zip(counts, [30_000, 250_000, 2_000_000], strict=True):
        assert abs(got / want - 1) < 0.05, counts


def test_each_configuration_runs_on_each_thread_count_and_scatter():
    from cosim.bench.mpm import expand, fixed_configs

    configs = fixed_configs(quick=True)
    rows = expand(configs, "cpu", [1, 16], ["serial", "coloured"])
    assert len(rows) == 4 * len(configs)
    assert [(r["threads"], r["scatter"]) for r in rows[:: len(configs)]] == [
        (1, "serial"), (1, "coloured"), (16, "serial"), (16, "coloured")
    ]  # fmt: skip
    assert all("threads" not in r and "scatter" not in r for r in expand(configs, "cuda", None, None))


def test_mpm_flags_that_do_not_go_together_are_refused_by_name():
    import pytest

    from cosim.bench import run_bench
    from cosim.bench.mpm_modes import check_mode
    from cosim.errors import InputError

    with pytest.raises(InputError, match="--threads sets CPU threads; --arch cuda"):
        check_mode(False, None, False, "cuda", [1, 2], None, None)
    with pytest.raises(InputError, match="--scatter fast: choose from serial, coloured, atomic"):
        check_mode(False, None, False, "cpu", None, ["serial", "fast"], None)
    with pytest.raises(InputError, match="--sizes and --particles"):
        check_mode(True, None, False, "cpu", None, None, 1000)
    with pytest.raises(InputError, match="options of `bench mpm`, not of `bench contact`"):
        run_bench("contact", Path("unused"), threads=[2])
    with pytest.raises(
        InputError, match="--arch is an option of `bench mpm` and `bench contact`, not of `bench cloth`"
    ):
        run_bench("cloth", Path("unused"), arch="cuda")


def test_a_peer_is_named_and_found_or_refused_with_the_fix(tmp_path):
    """`--peer` takes NAME=DIR for a known peer whose engine module is in DIR; otherwise the error names
    the flag and says how to get the checkout. It runs on its own sizes: --particles with it is refused."""
    import pytest

    from cosim.bench.mpm_modes import check_mode
    from cosim.bench.mpm_peer import MEASURE_SOFTMAC, peer_interpreter
    from cosim.errors import InputError

    with pytest.raises(InputError, match="--peer genesis=.*NAME one of softmac"):
        peer_interpreter(f"genesis={tmp_path}")
    with pytest.raises(InputError, match=r"no softmac/engine/mpm_simulator.py under .*clone https://github.com/"):
        peer_interpreter(f"softmac={tmp_path}")
    (tmp_path / "softmac" / "engine").mkdir(parents=True)
    (tmp_path / "softmac" / "engine" / "mpm_simulator.py").write_text("")
    peer = peer_interpreter(f"softmac={tmp_path}")
    assert peer.env["PYTHONPATH"].split(":")[0] == str(tmp_path) and peer.measure == MEASURE_SOFTMAC
    with pytest.raises(InputError, match="--peer compares its own sizes"):
        check_mode(False, None, False, "cpu", None, None, 30000, f"softmac={tmp_path}")


def test_a_baseline_comparison_keeps_each_thread_count_and_scatter_apart():
    """Runs of the same sizes with different --threads / --scatter are medians of their own, each
    version's against the other's of the same setting: median fwd rates 2 / 4 and 3 / 9 over the runs."""
    from cosim.bench.mpm_baseline import MEASURES, medians, setting

    sizes = {"dim": 3, "precision": "float32", "grid": "64^3", "particles": 29791}
    runs = []
    for cfg, base_fwd, cur_fwd in [({"threads": 2, "scatter": "atomic"}, [1, 2, 5], [4, 4, 3]),
                                   ({"scatter": "coloured"}, [3, 3, 1], [9, 8, 10])]:  # fmt: skip
        for version, rates in (("baseline", base_fwd), ("current", cur_fwd)):
            for rate in rates:
                runs.append({**sizes, "version": version, "setting": setting(cfg)} | dict.fromkeys(MEASURES, 1.0)
                            | {"fwd_Mpss": float(rate)})  # fmt: skip
    rows = {r["setting"]: r for r in medians(runs, "baseline")}
    assert sorted(rows) == ["2 threads, atomic", "coloured"]
    assert rows["2 threads, atomic"]["ratio_fwd_Mpss"] == 4 / 2
    assert rows["coloured"]["ratio_fwd_Mpss"] == 9 / 3
    assert setting({"dim": 3}) == "default"


def test_a_kernels_profile_splits_into_its_loops_in_their_order():
    """Taichi's records name a launch's parallel loops ``<kernel>_c<i>_<j>_kernel_<k>_<type>``: per kernel the
    loops come in the order k of the kernel's code (10 after 2), each summed over the kernel's template
    instances; a kernel of one loop is not split. Tasks are counted per run, serial ones apart."""
    from cosim.bench.kernel_profile import by_kernel, by_task, task_counts

    records = [
        ["_substep_fused_c84_0_kernel_10_range_for", 1.0, 3],
        ["_substep_fused_c84_0_kernel_2_range_for", 4.0, 3],
        ["_substep_fused_c84_1_kernel_2_range_for", 0.5, 3],
        ["_substep_fused_c84_0_kernel_0_serial", 0.25, 3],
        ["_grid_update_c12_0_kernel_0_range_for", 2.0, 3],
    ]
    tasks = by_task(records, "_substep_fused")
    assert tasks == [("kernel_0_serial", 0.25), ("kernel_2_range_for", 4.5), ("kernel_10_range_for", 1.0)]
    assert sum(ms for _, ms in tasks) == next(k[1] for k in by_kernel(records) if k[0] == "_substep_fused")
    assert by_task(records, "_grid_update") == []
    assert task_counts(records, "_substep_fused") == {"tasks": 12, "serial": 3}
    assert task_counts(records) == {"tasks": 15, "serial": 3}
