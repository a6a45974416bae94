"""NI-DAQmx proximity A/D: channel lists and options checked before any hardware, NI's own package and its errors.

No NI card or NI-DAQmx runtime is on this machine; the tests drive NI's real ``nidaqmx`` package up
to the point where it needs the runtime and check that what a user then sees is one line.
"""

from __future__ import annotations

import pytest

from driftlab.daq.nidaq import TERMINALS, NIDaqVolts, physical_channels
from driftlab.errors import InstrumentError, ValidationError


def test_physical_channel_lists():
    assert physical_channels("Dev1/ai0:4") == ("Dev1", [f"Dev1/ai{i}" for i in range(5)])
    assert physical_channels("PXI1Slot2/ai3, PXI1Slot2/ai7")[1] == ["PXI1Slot2/ai3", "PXI1Slot2/ai7"]
    for bad, needle in [
        ("Dev1/ao0", "write Dev1/ai0"),
        ("Dev1/ai4:0", "backwards"),
        ("Dev1/ai0,Dev2/ai1", "one device"),
        ("Dev1/ai0:2,Dev1/ai1", "each channel once"),
    ]:
        with pytest.raises(ValidationError, match=needle):
            physical_channels(bad)


def test_options_are_checked_before_the_card_is_touched():
    card = NIDaqVolts("Dev1/ai0:4", terminal="diff", samples=10, rate_hz=1000)
    assert card.n_channels == 5 and card.terminal == "DIFF"
    with pytest.raises(ValidationError, match="terminal"):
        NIDaqVolts("Dev1/ai0", terminal="GROUNDED")
    with pytest.raises(ValidationError, match="min_v"):
        NIDaqVolts("Dev1/ai0", min_v=5, max_v=0)
    with pytest.raises(ValidationError, match="indices"):
        card.read_volts([5])


def test_terminal_names_are_nidaqmx_s_own():
    constants = pytest.importorskip("nidaqmx.constants")
    assert set(TERMINALS) <= {t.name for t in constants.TerminalConfiguration}


def test_without_ni_daqmx_opening_is_one_line():
    pytest.importorskip("nidaqmx")
    with pytest.raises(InstrumentError) as err:
        NIDaqVolts("Dev1/ai0:4").open()
    msg = err.value.one_line()
    assert msg.startswith("NI-DAQmx") and "NI-DAQmx" in msg[9:] and "\n" not in msg


def test_a_rig_with_an_ni_card_reports_it_in_one_line(tmp_path, capsys):
    pytest.importorskip("nidaqmx")
    from driftlab.cli import main

    rig = tmp_path / "rig.yaml"
    rig.write_text(
        "name: ni\ninstruments:\n  proximity: {driver: nidaqmx, resource: 'Dev1/ai0:4', options: {samples: 10}}\n"
    )
    assert main(["rig", "check", str(rig)]) == 1
    (line,) = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("driftlab:")]
    assert line.startswith("driftlab: rig ni: proximity (nidaqmx at Dev1/ai0:4): NI-DAQmx")
