"""The notebook API (issue 35.9): `driftlab.connect(url)` against a real server and a real SQLite store.

Once through uvicorn on 127.0.0.1 (``driftlab serve`` in a subprocess, the fixture of test_server), once
through the app in-process (Starlette's TestClient, an httpx.Client over the ASGI app) for the cheaper
checks. The figures are checked against the seeded bundle's frames and the model document's numbers,
not against driftlab's own readers.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from fastapi.testclient import TestClient

import driftlab
from driftlab.api.app import create_app
from driftlab.errors import NotFoundError, ValidationError
from tests.api.helpers import MACHINE, TOKEN, Seeded, small_frames
from tests.api.test_server import server  # noqa: F401  (the uvicorn fixture)


def test_a_notebook_reads_a_running_server(server: str, seeded: Seeded) -> None:  # noqa: F811
    with driftlab.connect(server) as lab:
        camps = lab.campaigns()
        assert list(camps.index) == [seeded.campaign_id]
        assert camps.loc[seeded.campaign_id, "machine_id"] == MACHINE
        assert str(camps["started_at"].dt.tz) == "UTC"

        temps = lab.temperatures(seeded.campaign_id)
        expected, _, errors = small_frames()
        assert temps.attrs["unit"] == "°C"
        assert list(temps.columns) == ["time_s", "T1", "T2", "T49", "T50"]
        assert isinstance(temps.index, pd.DatetimeIndex) and temps.index.name == "time"
        assert temps.index[0] == pd.Timestamp("2026-03-02T08:00:00Z")
        assert (temps.index[1] - temps.index[0]).total_seconds() == expected["time_s"][1] - expected["time_s"][0]
        got = temps.reset_index(drop=True)
        for ch in ("T1", "T2", "T49", "T50"):
            np.testing.assert_allclose(got[ch].to_numpy(), expected[ch].to_numpy(), rtol=0, atol=1e-9, equal_nan=True)
        chans = ["T1", "T2", "T49", "T50"]
        assert got[chans].isna().sum().sum() == expected[chans].isna().sum().sum()

        errs = lab.errors(seeded.campaign_id)
        assert len(errs) == len(errors)
        np.testing.assert_allclose(errs["value"].to_numpy(), errors["value"].to_numpy(), atol=1e-12)
        rot = errs["term"].isin(["alpha", "beta", "gamma"])
        assert set(errs.loc[rot, "unit"]) <= {"rad"} and set(errs.loc[~rot, "unit"]) <= {"mm"}
        np.testing.assert_allclose(errs.loc[~rot, "value_um_or_urad"], errs.loc[~rot, "value"] * 1e3)
        dz = lab.errors(seeded.campaign_id, axis="Z", term="dz")
        assert len(dz) == int(((errors["axis"] == "Z") & (errors["term"] == "dz")).sum())

        model = lab.model(MACHINE)
        assert model.version == seeded.model_version and model.etag
        summary = model.summary()
        assert list(summary["param"]) == ["dz", "dx"]
        assert summary["unit"].tolist() == ["µm", "µm"] and summary["rmse_train"].tolist() == [0.5, 0.4]
        assert "temperature rise of T1" in summary.loc[0, "features"]


def test_predict_follows_the_documents_coefficients(seeded: Seeded) -> None:
    app = create_app(seeded.url, TOKEN)
    with TestClient(app) as http:
        lab = driftlab.connect("http://test", client=http)
        model = lab.model(MACHINE)
        # at home, T1 one degree above its reference moves dz by the coefficient (0.002 mm/°C = 2 µm),
        # T2 one degree above its own moves dx by 0.0005 mm/°C = 0.5 µm (the document's numbers)
        base = {"T1": 20.0, "T2": 21.0}
        p0 = model.predict(base)
        p1 = model.predict({**base, "T1": 21.0})
        p2 = model.predict({**base, "T2": 22.0})
        assert list(p0.columns) == ["alpha_urad", "beta_urad", "gamma_urad", "dx_um", "dy_um", "dz_um"]
        assert abs(p1["dz_um"][0] - p0["dz_um"][0]) == pytest.approx(2.0, rel=1e-6)
        assert abs(p2["dx_um"][0] - p0["dx_um"][0]) == pytest.approx(0.5, rel=1e-6)
        assert abs(p0["dz_um"][0]) == pytest.approx(1.0, rel=1e-6)  # the constant, 0.001 mm
        # a frame in, a frame out, row for row and on the same index
        temps = lab.temperatures(lab.campaigns().index[0])
        pred = model.predict(temps, pose=(100.0, 50.0, -20.0, 0.0, 0.0))
        assert pred.index.equals(temps.index) and len(pred) == len(temps)
        ok = temps[["T1", "T2"]].notna().all(axis=1).to_numpy()
        want = 1.0 + 2.0 * (temps["T1"].to_numpy()[ok] - 20.0)
        np.testing.assert_allclose(np.abs(pred["dz_um"].to_numpy()[ok]), np.abs(want), rtol=1e-6, atol=1e-9)
        assert pred["dz_um"][~ok].isna().all()  # a missing reading: no prediction, the rest predicted


def test_a_notebooks_mistakes_are_one_line_errors(seeded: Seeded) -> None:
    app = create_app(seeded.url, TOKEN)
    with TestClient(app) as http:
        lab = driftlab.connect("http://test", client=http)
        with pytest.raises(NotFoundError, match="ghost"):
            lab.model("ghost")
        with pytest.raises(NotFoundError, match="no channel T99"):
            lab.temperatures(seeded.campaign_id, channels=["T99"])
        with pytest.raises(ValidationError, match="axis must be one of"):
            lab.errors(seeded.campaign_id, axis="Q")
        model = lab.model(MACHINE)
        with pytest.raises(ValidationError, match="lack the model's channels T2"):
            model.predict({"T1": 20.0})
        with pytest.raises(ValidationError, match="pose must be X, Y, Z"):
            model.predict({"T1": 20.0, "T2": 21.0}, pose=(1.0, 2.0))
    with pytest.raises(ValidationError, match="base URL"):
        driftlab.connect("localhost:8765")
    assert math.isfinite(float(driftlab.__version__.split(".")[0]))
