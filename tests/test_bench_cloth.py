"""`cosim bench cloth`'s query part on a tiny case: the hash and brute-force kernels it times must find
the same faces, and its point cloud must put about 40 % of the points within the band (the share the
benchmark claims; a point spread uniformly over +-2.5 bands of a flat sheet lies within one band with
probability 1 / 2.5, less near the rim and on the ripples' slopes)."""

from __future__ import annotations

from cosim.bench import BENCHMARKS
from cosim.bench.cloth import measure_query


def test_cloth_bench_query_agrees_with_brute_force_at_the_stated_band_share():
    assert "cloth" in BENCHMARKS
    r = measure_query(faces=200, points=3000, repeat=1)  # raises if any point's face differs
    assert r["same_faces"] and r["faces"] >= 150
    assert 0.33 < r["within_band"] < 0.45, r["within_band"]
    assert r["hash_query_ms"] > 0 and r["brute_query_ms"] > 0
