"""The simulated rig as a whole: instruments coupled through one plant, and third-party Modbus clients."""

from __future__ import annotations

import minimalmodbus
import numpy as np
import pytest
from pyModbusTCP.client import ModbusClient

from bench.models.lozenge import PROTOTYPE_LAMBDA2P, electrostatic_force
from bench.models.lozenge_runs import static_force
from bench.models.membrane_runs import simulate_membrane
from tests.conftest import RIGS, ROOT, RunningRig, start_rig


def test_voltage_on_the_amplifier_moves_the_laser_as_the_model_predicts(thesis: RunningRig) -> None:
    """6 kV applied through the TREK/ADAM path at t = 1 s; the laser at t = 6 s against an offline Radau run."""
    amp, laser = thesis.inst.amplifier, thesis.inst.laser
    t_on = thesis.sim.clock.now()
    amp.set_voltage(6000.0)
    v_out = thesis.sim.plant.hv.gain * thesis.sim.plant.v_in  # after the ADAM's 12-bit quantisation
    thesis.advance(5.0)
    measured = laser.read_displacement().value
    params = thesis.rig.specimen.membrane()

    def step(t: np.ndarray) -> np.ndarray:
        return np.where(np.asarray(t) >= t_on, v_out, 0.0)

    model = simulate_membrane(params, step, t_on + 5.0, fs=1000.0, T=thesis.rig.specimen.temperature_K)
    assert model.displacement[-1] > 4e-3
    assert measured == pytest.approx(model.displacement[-1], abs=5e-6)  # fixed step vs Radau, noise


def test_voltage_changes_the_load_cell_force_by_the_electrostatic_force(lsdea_motor: RunningRig) -> None:
    """Motor to x = 100 mm, 30 s relaxation, then 6 kV: the load cell sees F_es(x, V) = −½V² dC/dx."""
    rig, inst = lsdea_motor, lsdea_motor.inst
    inst.motor.enable()
    inst.motor.move_to(0.055, 0.2, 2.0)
    inst.motor.wait_in_target()
    rig.advance(30.0)
    x = rig.rig.specimen.lsdea.x_at_motor_zero_m + inst.motor.read_position().value
    assert x == pytest.approx(0.100, abs=1e-7)
    f0 = inst.load_cell.read_force()
    params = rig.rig.specimen.lozenge()
    assert f0.value == pytest.approx(static_force(params, x), abs=0.03)  # branch relaxed after 30 s
    inst.amplifier.set_voltage(6000.0)
    v_out = rig.sim.plant.hv.gain * rig.sim.plant.v_in
    rig.advance(0.5)
    f1 = inst.load_cell.read_force()
    # physics.md §2.2: −F_es of prototype #1 peaks at x = l√(2/3) = 98.0 mm with 1.426 N at 7 kV; F_es ∝ V²
    # and is flat at its peak (at 100 mm within 0.5 %)
    assert params.lambda2p == PROTOTYPE_LAMBDA2P[1]
    expected = -1.426 * (v_out / 7000.0) ** 2
    assert electrostatic_force(x, v_out, params.pack())[0] == pytest.approx(expected, rel=5e-3)
    assert f1.value - f0.value == pytest.approx(expected, abs=0.03)  # 1-g divisions, 0.2-g noise
    v, _ = inst.amplifier.read_monitors()
    assert v.value == pytest.approx(v_out, abs=2.0)


def test_isotonic_rig_laser_follows_the_hung_mass(lsdea_isotonic: RunningRig) -> None:
    """5 kV DC on the hung-mass bench: the laser reading moves to the quasi-static equilibrium (B6)."""
    inst, head = lsdea_isotonic.inst, lsdea_isotonic.sim.twins["laser"].head
    x_rest = inst.laser.read_displacement().value * 1e3 - head.offset_mm
    assert x_rest == pytest.approx(66.04, abs=0.05)
    inst.amplifier.set_voltage(5000.0)
    lsdea_isotonic.advance(20.0)
    x_on = inst.laser.read_displacement().value * 1e3 - head.offset_mm
    assert x_on == pytest.approx(83.52, abs=0.3)  # the branch relaxes over τ = 1 s


def test_third_party_rtu_client_reads_the_simulated_modules(lsdea_motor_rtu: RunningRig) -> None:
    """minimalmodbus (its own RTU implementation on pyserial) against the pymodbus twins on the pty bus."""
    lsdea_motor = lsdea_motor_rtu
    io = minimalmodbus.Instrument(lsdea_motor.sim.port_map()["io"], 1)
    io.serial.baudrate, io.serial.timeout = 19200, 0.5
    assert io.read_registers(210, 2, functioncode=3) == [0x4024, 0x0000]
    io.write_register(0, 3071, functioncode=6)  # 5 V on the amplifier input
    assert lsdea_motor.sim.plant.v_in == pytest.approx(5.0, abs=3e-3)
    io.serial.close()
    scale = minimalmodbus.Instrument(lsdea_motor.sim.port_map()["scale"], 1)
    scale.serial.baudrate, scale.serial.timeout = 19200, 0.5
    regs = scale.read_registers(0, 7, functioncode=4)
    gross_g = (regs[0] << 16) | regs[1]
    assert gross_g == pytest.approx(lsdea_motor.sim.plant.last.force[0] / 9.80665 * 1e3, abs=2)
    counter = regs[5] & 0x0F
    scale.write_register(0, 2, functioncode=6)  # tare
    assert scale.read_register(5, functioncode=4) & 0x0F == (counter + 1) & 0x0F
    scale.serial.close()


def test_third_party_tcp_client_reads_the_simulated_modules() -> None:
    """pyModbusTCP (independent Modbus TCP client) against the twins served on loopback."""
    r = start_rig("lsdea-motor-sim", simulation={"seed": 1, "modbus_transport": "tcp"})
    try:
        host, port = r.sim.port_map()["scale"].removeprefix("tcp://").split(":")
        client = ModbusClient(host=host, port=int(port), unit_id=1, auto_open=True, timeout=1.0)
        regs = client.read_input_registers(0, 5)
        assert regs is not None and regs[4] & 0x04  # stable bit
        client.close()
        host, port = r.sim.port_map()["io"].removeprefix("tcp://").split(":")
        client = ModbusClient(host=host, port=int(port), unit_id=2, auto_open=True, timeout=1.0)
        assert client.read_holding_registers(210, 2) == [0x4017, 0x5000]
        client.close()
    finally:
        r.inst.close()
        r.sim.stop()


def test_the_dry_run_and_the_simulated_rig_share_one_plant_factory_with_the_rigs_amplifier() -> None:
    """Issue 9: one plant factory (bench.rig.plant_for). The dry run used a default output stage; both now take
    the rig's amplifier. A 10/40A-HS delivers 40 mA DC at ±10 kV with gain 1000 V/V (TREK HS datasheet)."""
    from bench.core.clock import VirtualClock
    from bench.protocol.predict import build_plant
    from bench.protocol.program import compile_program
    from bench.protocol.schema import load_protocol
    from bench.rig import RigConfig, load_rig
    from bench.runtime.sim_rig import SimRig

    base = load_rig(RIGS / "lsdea-motor-sim.toml")
    assert base.amplifier is not None
    rig = RigConfig.model_validate({**base.model_dump(),
                                    "amplifier": {**base.amplifier.model_dump(), "model": "10/40A-HS"}})
    protocol = load_protocol(ROOT / "protocols" / "short" / "lsdea-isometric-short.toml")
    dry = build_plant(compile_program(protocol, rig), VirtualClock())
    sim = SimRig(rig, virtual=True)
    for plant in (dry, sim.plant):
        assert (plant.hv.max_current, plant.hv.max_output, plant.hv.gain) == (40e-3, 10e3, 1000.0)
        assert type(plant.specimen) is type(sim.plant.specimen)


def test_a_motor_position_read_does_not_wait_for_an_integration_under_way() -> None:
    """The drive's position is kinematic (its motion profile): a LinMot poll must not queue behind the DAQ twin
    integrating the specimen under the plant's lock (it did, and the isometric campaign ran ~35 % slower)."""
    import threading

    from bench.core.clock import VirtualClock
    from bench.core.motion import MotionProfile
    from bench.core.plant import HVStage, Plant
    from bench.models.membrane import MembraneParams

    clock = VirtualClock()
    plant = Plant(clock, MembraneParams(), hv=HVStage())
    plant.set_motion(lambda t, p, v: MotionProfile.plan(t, p, v, 0.01, 0.1, 1.0, 1.0))
    clock.advance(0.05)
    expected = plant.motion.evaluate(0.05)
    got: list[tuple[float, float]] = []
    with plant.lock:  # an integration under way in another thread holds it
        reader = threading.Thread(target=lambda: got.append(plant.motor_state()))
        reader.start()
        reader.join(timeout=5.0)
        assert not reader.is_alive() and got == [(float(expected[0]), float(expected[1]))]
