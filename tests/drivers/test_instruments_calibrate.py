"""``nanodrift calibrate --config`` on the simulated cell's physics read through the instrument plugins: the
thermocouples from a DCON module on a pty (one ``#AA`` line a poll), the position from an attocube IDS on TCP
127.0.0.1 (pm), the stage driven by the Modbus analog output of ``helpers.emulated_cell``. The model it
identifies has the stage's gain, and every temperature it was fitted on came from the module's line."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.emulated_cell import (
    AO_ADDRESS,
    AO_VOLTS_PER_COUNT,
    CONTROLLER_TIMEOUT_S,
    THERMOCOUPLES,
    VOLTS_PER_UM,
    EmulatedCell,
)

from nanodrift.calibration.dataset import read_csv
from nanodrift.cli import main
from nanodrift.drivers.testing import DconBusEmulator, DconModule, IdsEmulator
from nanodrift.model.model import load_model

FAST = "cycles = 1\nrise_s = 0.05\nhold_s = 0.2\naverage_s = 0.1\n"


def config_text(emulated: EmulatedCell, rs485: str, ids_port: int) -> str:
    sensors = "".join(f'[[sensors]]\nname = "{name}"\nkind = "dcon"\nhub = "rs485"\naddress = 5\nchannel = {c}\n'
                      "interval_s = 0.05\n" for c, name in enumerate(THERMOCOUPLES))
    sensors += ('[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "attocube_ids"\n'
                f'host = "127.0.0.1"\nport = {ids_port}\nids_axis = 2\ninterval_s = 0.02\n'
                f"timeout_s = {CONTROLLER_TIMEOUT_S}\n")
    return ('cell = "instruments"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:0"]\nmulticast_scouting = false\n'
            f"[actuator]\nvolts_per_um = {VOLTS_PER_UM}\nv_min = -1.0\nv_max = 11.0\n"
            f'kind = "modbus"\nhub = "module"\naddress = {AO_ADDRESS}\ndata_type = "int16"\n'
            f"scale = {AO_VOLTS_PER_COUNT}\nverify = true\n"
            f"[procedure]\n{FAST}"
            f'[[hubs]]\nname = "module"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {emulated.modbus.port}\n'
            f'timeout_s = {CONTROLLER_TIMEOUT_S}\n[[hubs]]\nname = "rs485"\ntype = "serial"\nport = "{rs485}"\n'
            f"timeout_s = {CONTROLLER_TIMEOUT_S}\n"
            f"{sensors}")


def test_calibrate_reads_the_dcon_module_and_the_ids(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with EmulatedCell(tmp_path, speed=1000.0) as emulated:

        def thermocouples() -> list[float]:
            with emulated.lock:
                readings = emulated.cell.read(THERMOCOUPLES)
            return [readings[name].value for name in THERMOCOUPLES]

        module = DconModule(5, [0.0] * 8, name="4018+", follow=lambda: [*thermocouples(), 0.0, 0.0, 0.0, 0.0])
        bus = DconBusEmulator(tmp_path / "ttyRS485", [module])
        ids = IdsEmulator()
        ids.axes[2].follow = lambda: emulated.position_um() * 1e6  # the stage as the IDS's axis 2 sees it, in pm
        try:
            config = tmp_path / "instruments.toml"
            config.write_text(config_text(emulated, bus.port, ids.port))
            model_path, data = tmp_path / "model.json", tmp_path / "cal.csv"
            assert main(["calibrate", "--config", str(config), "--out", str(model_path), "--data", str(data)]) == 0
            capsys.readouterr()
        finally:
            bus.close()
            ids.stop()

    recorded = read_csv(data)
    assert len(recorded) == 17 and recorded.extra["valid"].all()
    # the temperatures came from the module's #05 lines, every poll one line for all four channels
    for name in THERMOCOUPLES:
        assert 15.0 < float(recorded.channels[name].mean()) < 35.0
    assert {line for line in bus.requests if line.startswith("#")} == {"#05"}
    assert ("com.attocube.ids.displacement.getAxisDisplacement", [2]) in ids.requests
    model = load_model(model_path)
    coefs = {ft.term.name: ft.coef for ft in model.terms}
    assert coefs.get("x") == pytest.approx(1.0, abs=0.01)  # the stage's gain, identified through the IDS (pm -> um)
    # ~25 nm idle; the physics runs at 1000x wall time, so a loaded machine's late poll adds tens of simulated
    # seconds of drift (a broken fit is hundreds of nm)
    assert model.fit["residual_rms_nm"] < 80.0
