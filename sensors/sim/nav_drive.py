"""The simulated Eddie drive train for `rgbdnav navigate`, in simulated time.

Commands take the path a real robot's do: a body twist (v, w) becomes GOSPD wheel speeds
(:func:`sensors.eddie.wheel_speeds`: v -+ w track / 2 in encoder positions per second, both
wheels scaled down together above ``robot.max_wheel_speed``), encoded as the board's
``GOSPD <left> <right>\\r`` line and fed to the firmware emulator
(:class:`sensors.eddie_emulator.EddieEmulator`, in process, its clock being the simulation's).
The emulator ramps each wheel at its ACC limit and keeps the encoder counts.

The ground does not follow the encoders exactly (the same error model as the RGB-D simulator,
``SimConfig``): each wheel's true diameter differs from nominal by ``wheel_diameter_error``, the
true track by ``track_width_error``, and each wheel slips by a relative amount that is a
first-order Gauss-Markov process (std ``wheel_slip``, correlation time ``slip_correlation_time``).
The true pose integrates the wheels' true ground travel at ``physics_rate``. :meth:`ticks` gives
the counts as DIST would report them; wheel odometry (:class:`slam.diff_drive.WheelOdometry`)
integrates them with the *nominal* geometry, so it drifts like a real robot's. Gear backlash is
not modelled.
"""

from __future__ import annotations

import numpy as np

from sensors.config import RobotConfig, SimConfig
from sensors.eddie import encode_command, wheel_speeds
from sensors.eddie_emulator import EddieEmulator
from sensors.sim.motion import diff_drive_step, gauss_markov_step
from sensors.types import NS_PER_S, SensorError, WheelTicks

ACK = b"\r"  # the board's reply to a command that sets something


class EmulatedDrive:
    """The robot's wheels: GOSPD into the board emulator, true motion with slip, DIST back.

    ``pose`` is the true base_link pose in the world; :meth:`ticks` is what the board reports.
    """

    def __init__(
        self, robot: RobotConfig, sim: SimConfig, start: np.ndarray, rng: np.random.Generator
    ) -> None:
        self.robot, self.sim, self.rng = robot, sim, rng
        self.t_ns = 0
        self.board = EddieEmulator(robot, time_source=lambda: self.t_ns / NS_PER_S)
        self.pose = np.asarray(start, dtype=np.float64).copy()
        self.physics_ns = round(NS_PER_S / sim.physics_rate)
        m = robot.metres_per_tick
        self.true_m_per_position = np.array(
            [m * (1.0 + sim.wheel_diameter_error[0]), m * (1.0 + sim.wheel_diameter_error[1])]
        )  # [m/position] left, right
        self.true_track = robot.track_width * (1.0 + sim.track_width_error)  # [m]
        self.slip = rng.standard_normal(2) * sim.wheel_slip  # stationary start
        self.speeds = np.zeros(2)  # [positions/s] wheel speeds at t_ns
        self.sent = (0, 0)  # last GOSPD (left, right) [positions/s]
        self.gospd_lines = 0

    def command(self, v: float, w: float) -> tuple[int, int]:
        """Send the twist (v [m/s], w [rad/s]) as GOSPD when the wheel speeds change; returns
        the (left, right) speeds [positions/s] in force."""
        speeds = wheel_speeds(v, w, self.robot)
        if speeds != self.sent:
            reply = self.board.feed(encode_command("GOSPD", *speeds))
            if reply != ACK:
                raise SensorError(f"GOSPD {speeds}: board emulator replied {reply!r}")
            self.sent = speeds
            self.gospd_lines += 1
        return self.sent

    def advance(self, dt_ns: int) -> None:
        """Let ``dt_ns`` of simulated time pass in physics steps: wheel speeds from the board,
        ground travel with the true geometry and slip, the true pose integrated."""
        end = self.t_ns + dt_ns
        sim = self.sim
        while self.t_ns < end:
            h_ns = min(self.physics_ns, end - self.t_ns)
            h = h_ns / NS_PER_S
            self.t_ns += h_ns
            now = np.array(self.board.speeds())
            # The board ramps linearly within a step: the trapezoid is its exact travel.
            positions = 0.5 * (self.speeds + now) * h
            self.speeds = now
            ground = positions * self.true_m_per_position * (1.0 + self.slip)
            self.pose = diff_drive_step(self.pose, ground[0], ground[1], self.true_track)
            self.slip = gauss_markov_step(
                self.slip, sim.wheel_slip, sim.slip_correlation_time, h, self.rng.standard_normal(2)
            )

    def ticks(self) -> WheelTicks:
        """Cumulative encoder counts now, as DIST reports them."""
        left, right = self.board.distances()
        return WheelTicks(self.t_ns, left, right)

    def true_twist(self) -> tuple[float, float]:
        """Nominal body twist (v [m/s], w [rad/s]) of the wheels' current speeds."""
        vl, vr = self.speeds * self.robot.metres_per_tick
        return 0.5 * (vl + vr), (vr - vl) / self.robot.track_width


__all__ = ["EmulatedDrive"]
