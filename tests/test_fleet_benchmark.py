"""The fleet benchmark's code path at a tiny scale (the benchmark itself never runs in the suite).

One machine, two one-day campaigns, a few drift queries and one fit by one worker process: the
load with its raw-COPY baseline, the API's drift route, the queue and the JSON line all run, on
a throwaway PostgreSQL cluster of the benchmark's own (missing PostgreSQL fails here, never skips).
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "fleet.py"

pytestmark = pytest.mark.postgres


def test_fleet_benchmark_smoke(capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("fleet_benchmark", BENCH)
    assert spec is not None and spec.loader is not None
    fleet = importlib.util.module_from_spec(spec)
    sys.modules["fleet_benchmark"] = fleet
    try:
        spec.loader.exec_module(fleet)
        assert (
            fleet.main(
                [
                    "--machines",
                    "1",
                    "--days",
                    "2",
                    "--campaign-days",
                    "1",
                    "--sweep-h",
                    "1",
                    "--queries",
                    "3",
                    "--workers",
                    "1",
                    "--fit-jobs",
                    "1",
                    "--fit-campaigns",
                    "1",
                ]
            )
            == 0
        )
    finally:
        sys.modules.pop("fleet_benchmark", None)
    line = capsys.readouterr().out.strip().splitlines()[-1]
    figures = json.loads(line)
    assert figures["benchmark"] == "fleet"
    assert figures["campaigns"] == 2 and figures["readings"] == 2 * 721 * 50
    assert figures["import_ratio_to_raw_copy"] > 0 and figures["raw_copy_rows_per_s"] > 0
    assert figures["drift_queries"] == 3 and figures["drift_points_per_query_median"] > 0
    assert figures["drift_statement_partitions_read"] == 1  # pruning, on the benchmark's own database
    assert figures["fit_jobs"]["1"]["fits"] == 1
