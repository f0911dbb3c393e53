"""Every `cosim bench` report starts with the command line, the date (UTC) and the hardware
(``cosim.bench.report``), so that a report copied into docs/bench/ says what produced it and where."""

import os
from datetime import datetime, timedelta, timezone
from pathlib import Path

from cosim.bench.report import bench_command, git_commit, markdown_table, report_header
from cosim.hardware import hardware_line


def test_the_header_names_the_command_the_utc_date_and_the_hardware():
    then = datetime(2026, 12, 5, 9, 30, tzinfo=timezone(timedelta(hours=2)))  # 07:30 UTC
    header = report_header("cosim bench contact --repeat 5", now=then)
    lines = header.splitlines()
    assert lines[0] == "# `cosim bench contact --repeat 5`"
    assert "- date: 2026-12-05 07:30 UTC" in lines
    assert f"- hardware: {hardware_line()}" in lines
    commit = git_commit()
    assert (f"- cosim: commit {commit}" in lines) if commit else not any(line.startswith("- cosim") for line in lines)
    assert header.endswith("\n\n")  # the report's own text follows after a blank line


def test_the_command_line_is_written_back_from_the_options():
    """Options at their defaults are left out; a repeated option (``--scene``) is written once per value."""
    assert bench_command("contact", out=Path("out/bench"), quick=True, repeat=3, workers=2) == (
        "cosim bench contact --quick --workers 2"
    )
    assert bench_command("long", out=Path("/tmp/a b"), steps=500, scene=["dam_break_2d", "pour_water"]) == (
        "cosim bench long --out '/tmp/a b' --steps 500 --scene dam_break_2d --scene pour_water"
    )
    assert bench_command("fuzz", count=200, seed=0, sizes=False, baseline=None) == "cosim bench fuzz"


def test_a_table_keeps_the_formats_but_not_the_widths():
    rows = [{"n": 3, "rate": 1.23456}]
    assert markdown_table(rows, [("n", "n", ">5"), ("rate", "M/s", ">8.2f")]) == [
        "| n | M/s |",
        "|---|---|",
        "| 3 | 1.23 |",
    ]


def test_a_bench_writes_its_report_with_the_header(tmp_path, monkeypatch):
    """``cosim bench fuzz`` through ``run_bench`` (the CLI's path), its cases replaced by made-up records:
    fuzz.md starts with the command line the options make, then the date and the hardware."""
    from cosim.bench import fuzz, run_bench

    def made_up(seeds, workers=1, log_dir=None, on_record=None, **_):
        records = [fuzz.FuzzRecord(s, **fuzz.describe(fuzz.random_scene(s)), outcome="ran", seconds=1.0) for s in seeds]
        for r in records:
            on_record(r)
        return records

    monkeypatch.setattr(fuzz, "run_fuzz", made_up)
    out = tmp_path / "bench"
    assert run_bench("fuzz", out, count=2, seed=7, workers=1) == 0
    lines = (out / "fuzz.md").read_text().splitlines()
    assert lines[0] == f"# `cosim bench fuzz --out {out} --count 2 --seed 7 --workers 1`"
    assert lines[2].startswith("- date: ") and lines[2].endswith(" UTC")
    assert lines[3] == f"- hardware: {hardware_line()}"
    assert "| ran | 2 |" in lines


def test_the_hardware_line_names_the_gpus_nvidia_smi_lists_and_none_without_it(tmp_path, monkeypatch):
    """Two GPUs (a stand-in nvidia-smi on the PATH) are named once with their count; no tool, no GPU."""
    from cosim.hardware import gpu_names

    fake = tmp_path / "nvidia-smi"
    fake.write_text("#!/bin/sh\necho 'NVIDIA H200'\necho 'NVIDIA H200'\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}:{os.environ['PATH']}")
    gpu_names.cache_clear()
    try:
        assert ", GPU 2 x NVIDIA H200, Python" in hardware_line()
        monkeypatch.setenv("PATH", str(tmp_path / "nowhere"))
        gpu_names.cache_clear()
        assert "GPU" not in hardware_line()
    finally:
        gpu_names.cache_clear()
