"""Simulated devices: a mobile robot on a plane and a noisy sensor.

They are ordinary Resources (the one way services are written) and carry the
standard property sets: every mobile robot has ``location``, ``velocity``,
``actuators``, ``sensors`` and ``behaviors`` (with ``behaviors.moveto``);
every sensor has ``location`` and ``data``. All changes happen by attribute
assignment on the event loop, so a Listen hears each of them.

A robot carries a temperature sensor (``sensors.temperature``) that reads the simulated
world's temperature field (:mod:`services.apps.temperature_field`) where the robot is, with
seeded Gaussian noise, ``temperature_hz`` times a second while it moves and once where it
starts: a standing robot changes nothing.

A robot is driven in one of two ways, and each cancels the other: toward a
target (``behaviors.moveto``) or by a velocity command (a Set of ``velocity``,
the teleoperation of a joystick or a web page). Both move it in the world
frame, the frame of ``location``; a command holds only while it is renewed.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Mapping, Sequence
from typing import Annotated, Any

import numpy as np

from services.apps.temperature_field import TemperatureField
from services.kernel.core import Prop, Resource, functional
from services.kernel.errors import InvalidArgument
from services.kernel.values import Marker, Vector, format_number

__all__ = ["Actuators", "Behaviors", "Sensors", "SimRobot", "SimSensor"]

#: Highest simulation rate accepted: above it the loop's timer resolution and
#: the two shared cores, not the model, decide the motion.
MAX_TICK_HZ = 1000.0
#: Fastest cruise speed accepted, m/s (well beyond any indoor robot; tests use it to finish quickly).
MAX_SPEED = 1000.0
#: Charge used per metre driven: a full battery lasts 1 km.
BATTERY_PER_METRE = 0.001
#: Reference frames ``behaviors.moveto`` understands.
FRAMES = ("world", "robot")
#: Fastest turn a velocity command may ask for, rad/s (a robot spinning faster is a centrifuge).
MAX_TURN_RATE = 100.0
#: Seconds a velocity command holds without a renewal, as ROS cmd_vel watchdogs commonly use.
DEFAULT_VELOCITY_TIMEOUT = 0.5
#: Bounds of ``velocity_timeout``: shorter than a loopback round trip a command could never be
#: renewed in time; longer than a minute a lost operator leaves the robot driving blind.
MIN_VELOCITY_TIMEOUT = 0.05
MAX_VELOCITY_TIMEOUT = 60.0
#: Distance between the left and right wheels, m: turns the commanded turn rate into wheel speeds.
WHEEL_TRACK = 0.3
#: Readings a second of a robot's temperature sensor while it moves: the rate of a SimSensor.
DEFAULT_TEMPERATURE_HZ = 5.0
#: Standard deviation of the temperature sensor's noise, degrees Celsius (a cheap digital sensor).
DEFAULT_TEMPERATURE_NOISE = 0.05


def _six(values: Sequence[float] | Vector, what: str, axes: str) -> Vector:
    """A 6-vector from 2, 3 or 6 numbers; the missing elements are zeros. ``axes`` names them."""
    try:
        numbers = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgument(f"{what} must be 2, 3 or 6 numbers, got {values!r}") from None
    if numbers.ndim != 1 or len(numbers) not in (2, 3, 6) or not np.all(np.isfinite(numbers)):
        small = numbers.ndim == 1 and numbers.size <= 12
        shown = "(" + " ".join(f"{x:g}" for x in numbers.tolist()) + ")" if small else repr(values)[:80]
        raise InvalidArgument(f"{what} must be 2, 3 or 6 finite numbers ({axes}), got {shown}")
    six = np.zeros(6)
    six[: len(numbers)] = numbers
    return six


def _pose(values: Sequence[float] | Vector, what: str) -> Vector:
    """A 6-vector pose from 2, 3 or 6 numbers (x y, x y z, or x y z roll pitch yaw)."""
    return _six(values, what, "x y [z [roll pitch yaw]]")


def _rate(value: float, what: str, low: float, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
        raise InvalidArgument(
            f"{what} must be a number from {format_number(low)} to {format_number(high)}, got {value!r}"
        )
    return float(value)


class _Ticker:
    """Wakes at a fixed rate on the loop clock; a late wake-up shortens the next sleep (no drift)."""

    def __init__(self, hz: float) -> None:
        self.period = 1.0 / hz
        self._next: float | None = None
        self._last = 0.0
        # The last wake-up came before its tick (at ``not_after``): that tick is still to come.
        self._held = False
        self._wake = asyncio.Event()

    def restart(self) -> None:
        self._next = None

    def set_rate(self, hz: float) -> None:
        self.period = 1.0 / hz
        self._next = None
        self._wake.set()  # a long sleep at the old rate ends now

    async def wait(self, not_after: float | None = None) -> float:
        """Sleep until the next tick, or until the loop time ``not_after`` if that is sooner.

        Returns the seconds since the previous wake-up.
        """
        loop = asyncio.get_running_loop()
        now = loop.time()
        if self._next is None:
            self._next = self._last = now
            self._next += self.period
        elif not self._held:
            self._next += self.period
        if self._next < now:  # fell more than a tick behind: skip the missed ticks instead of bursting
            self._next = now + self.period
        wake_at, self._held = self._next, False
        if not_after is not None and not_after < wake_at:
            wake_at, self._held = not_after, True
        self._wake.clear()
        try:
            async with asyncio.timeout(max(0.0, wake_at - now)):
                await self._wake.wait()
        except TimeoutError:
            pass
        now = loop.time()
        dt, self._last = now - self._last, now
        return dt


class Actuators(Resource):
    """What the robot can switch or drive."""

    led: Annotated[bool, Prop(doc="status light on top of the robot")] = False
    wheels: Annotated[
        Vector, Prop(readonly=True, unit="m/s", length=2, resolution=0.01, doc="left and right wheel speeds")
    ]

    def __init__(self) -> None:
        self.wheels = np.zeros(2)


class Sensors(Resource):
    """What the robot senses about itself."""

    battery: Annotated[
        float, Prop(readonly=True, gui="gauge", minimum=0, maximum=1, resolution=0.001, doc="charge left")
    ]
    bumper: Annotated[bool, Prop(readonly=True, doc="true while the bumper touches something")] = False
    temperature: Annotated[
        float,
        Prop(
            readonly=True,
            gui="plot",
            unit="degC",
            resolution=0.1,
            doc="air temperature where the robot is, degrees Celsius",
        ),
    ]

    def __init__(self, battery: float = 1.0, temperature: float = 20.0) -> None:
        self.battery = battery
        self.temperature = temperature


class Behaviors(Resource):
    """What the robot can be asked to do."""

    def __init__(self, robot: SimRobot) -> None:
        self._robot = robot

    @functional(doc="drive to the target marker's location (ends a velocity command)")
    def moveto(self, target: Marker, *, frame: str = "world") -> None:
        """Drive to ``<marker><location>(x y ...)</location></marker>``, given in ``frame``."""
        location = target.location
        if location is None:
            raise InvalidArgument(
                "the target marker has no location: send <marker><location>(x y)</location></marker>"
            )
        if not 2 <= len(location) <= 6:
            raise InvalidArgument(f"the target location must have 2 to 6 numbers, got {len(location)}")
        if frame not in FRAMES:
            raise InvalidArgument(f"unknown frame {frame!r}: use one of {', '.join(FRAMES)}")
        self._robot.drive_to(location, frame)

    # Also the lifecycle hook's name: being functional, it is the property only (see Resource.start).
    @functional(doc="stop where the robot is (ends a moveto or a velocity command)")
    async def stop(self) -> None:
        """Stop now; the current target or velocity command is dropped."""
        self._robot.halt()


class SimRobot(Resource):
    """A simulated mobile robot on a plane, with the standard mobile-robot property set.

    ``behaviors.moveto`` drives it in a straight line toward its target at
    ``speed``, heading toward it, and stops exactly on it. A Set of
    ``velocity`` (vx vy [vz [wx wy wz]], m/s and rad/s, in the world frame
    like ``location``) drives it at that velocity instead: the linear part is
    scaled down to ``max_speed``, the turn rate clipped to ``max_turn_rate``,
    roll and pitch rates are zero, and the heading turns at wz. A command
    holds only while it is renewed: ``velocity_timeout`` seconds after the
    last Set the robot stops by itself. Each of the two cancels the other.
    A standing robot changes nothing (and sends nothing to listeners).

    ``sensors.temperature`` reads ``temperature`` (a field ``{ base, spots }``, see
    :class:`services.apps.temperature_field.TemperatureField`; by default the demo world's) where
    the robot is, with noise of ``temperature_noise`` degC (seeded by ``seed``), every
    ``1 / temperature_hz`` seconds of driving.
    """

    resource_type = "mobile_robot"

    location: Annotated[
        Vector,
        Prop(
            readonly=True,
            gui="pose",
            unit="m, rad",
            length=6,
            resolution=0.01,
            doc="x y z roll pitch yaw, world frame",
        ),
    ]
    speed: Annotated[
        float,
        Prop(
            minimum=0.0,
            maximum=MAX_SPEED,
            unit="m/s",
            resolution=0.01,
            gui="slider",
            doc="cruise speed of moveto",
        ),
    ]
    max_speed: Annotated[
        float,
        Prop(
            minimum=0.0,
            maximum=MAX_SPEED,
            unit="m/s",
            resolution=0.01,
            gui="slider",
            doc="fastest linear speed a velocity command gets; a faster one is scaled down",
        ),
    ]
    max_turn_rate: Annotated[
        float,
        Prop(
            minimum=0.0,
            maximum=MAX_TURN_RATE,
            unit="rad/s",
            resolution=0.01,
            gui="slider",
            doc="fastest turn a velocity command gets; a faster one is clipped",
        ),
    ]
    velocity_timeout: Annotated[
        float,
        Prop(
            minimum=MIN_VELOCITY_TIMEOUT,
            maximum=MAX_VELOCITY_TIMEOUT,
            unit="s",
            doc="a velocity command not renewed by a Set within this time ends: the robot stops",
        ),
    ]
    actuators: Actuators
    sensors: Sensors
    behaviors: Behaviors

    def __init__(
        self,
        *,
        start: Sequence[float] = (0.0, 0.0),
        speed: float = 0.5,
        tick_hz: float = 20.0,
        max_speed: float = 1.0,
        max_turn_rate: float = 2.0,
        velocity_timeout: float = DEFAULT_VELOCITY_TIMEOUT,
        temperature: Mapping[str, Any] | None = None,
        temperature_hz: float = DEFAULT_TEMPERATURE_HZ,
        temperature_noise: float = DEFAULT_TEMPERATURE_NOISE,
        seed: int | None = None,
    ) -> None:
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise InvalidArgument(f"seed must be an integer, got {seed!r}")
        self.location = _pose(start, "start")
        self._velocity = np.zeros(6)
        self.speed = _rate(speed, "speed", 0.0, MAX_SPEED)
        self.max_speed = _rate(max_speed, "max_speed", 0.0, MAX_SPEED)
        self.max_turn_rate = _rate(max_turn_rate, "max_turn_rate", 0.0, MAX_TURN_RATE)
        self.velocity_timeout = _rate(
            velocity_timeout, "velocity_timeout", MIN_VELOCITY_TIMEOUT, MAX_VELOCITY_TIMEOUT
        )
        self._field = TemperatureField.from_options(temperature)
        self._reading_period = 1.0 / _rate(temperature_hz, "temperature_hz", 0.1, MAX_TICK_HZ)
        self._temperature_noise = _rate(temperature_noise, "temperature_noise", 0.0, 1e3)
        self._rng = np.random.default_rng(seed)
        # Seconds driven since the last temperature reading.
        self._since_reading = 0.0
        self.actuators = Actuators()
        self.sensors = Sensors(temperature=self._read_temperature())
        self.behaviors = Behaviors(self)
        self._tick_hz = _rate(tick_hz, "tick_hz", 0.1, MAX_TICK_HZ)
        self._charge = 1.0
        self._target: Vector | None = None
        self._command: Vector | None = None
        # Seconds the velocity command has run since it was last renewed.
        self._command_age = 0.0
        self._go = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    @property
    def velocity(
        self,
    ) -> Annotated[
        Vector,
        Prop(
            gui="vector",
            unit="m/s, rad/s",
            length=6,
            doc="velocity vx vy vz wx wy wz in the world frame; Set it to drive, "
            "clipped to max_speed and max_turn_rate, renewed within velocity_timeout",
        ),
    ]:
        """The robot's velocity now: what moveto drives at, or the velocity command it follows."""
        return self._velocity

    @velocity.setter
    def velocity(self, command: Vector) -> None:
        self.command_velocity(command)

    # -- used by Behaviors and the velocity property --------------------------------

    def drive_to(self, location: Vector, frame: str) -> None:
        """Set the target: ``location`` holds x y [z ...] in ``frame`` (orientation is ignored).

        A velocity command in progress ends.
        """
        target = self.location[:3].copy()
        n = min(len(location), 3)
        if frame == "robot":
            yaw = self.location[5]
            x, y = location[0], location[1]
            target[0] += x * math.cos(yaw) - y * math.sin(yaw)
            target[1] += x * math.sin(yaw) + y * math.cos(yaw)
            if n == 3:
                target[2] += location[2]
        else:
            target[:n] = location[:n]
        self._command = None
        self._target = target
        self._go.set()

    def clip_velocity(self, command: Sequence[float] | Vector) -> Vector:
        """The velocity this robot follows for ``command`` (2, 3 or 6 numbers).

        The linear part keeps its direction and is scaled down to ``max_speed``;
        the turn rate is clipped to ``max_turn_rate``; a robot on a plane does
        not roll or pitch, so those rates are zero.
        """
        clipped = _six(command, "velocity", "vx vy [vz [wx wy wz]], m/s and rad/s")
        linear = float(np.linalg.norm(clipped[:3]))
        if linear > self.max_speed:
            clipped[:3] *= self.max_speed / linear
        clipped[3:5] = 0.0
        clipped[5] = min(max(clipped[5], -self.max_turn_rate), self.max_turn_rate)
        return clipped

    def command_velocity(self, command: Sequence[float] | Vector) -> None:
        """Drive at ``command``, clipped (see :meth:`clip_velocity`), for ``velocity_timeout`` seconds.

        Each call renews the command; a target of moveto is dropped. A command
        of zeros stops the robot at once.
        """
        clipped = self.clip_velocity(command)
        self._target = None
        if not np.any(clipped):
            self.halt()
            return
        self._command = clipped
        self._command_age = 0.0
        self._report_velocity(clipped)
        speed = float(np.linalg.norm(clipped[:2]))
        turn = clipped[5] * WHEEL_TRACK / 2
        self.actuators.wheels = np.array([speed - turn, speed + turn])
        self._go.set()

    def halt(self) -> None:
        """Drop the target or the velocity command and stand still."""
        self._target = None
        self._command = None
        self._go.clear()
        self._standstill()

    # -- simulation ----------------------------------------------------------------

    async def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._drive(), name="sim-robot motion")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None

    def advance(self, dt: float) -> None:
        """Move as the robot does in ``dt`` seconds: toward its target, or at its velocity command.

        The motion task calls it on every tick; a test may call it to run the
        simulation on a clock of its own.
        """
        if self._command is not None:
            self._coast(dt)
        elif self._target is not None:
            self._step(dt)
        else:
            return
        self._since_reading += dt
        if self._since_reading >= self._reading_period:
            self._since_reading = 0.0
            self.sensors.temperature = self._read_temperature()

    def _read_temperature(self) -> float:
        """The temperature sensor's reading where the robot is now, to 0.01 degC."""
        true = self._field.at(float(self.location[0]), float(self.location[1]))
        noise = float(self._rng.normal(0.0, self._temperature_noise)) if self._temperature_noise else 0.0
        return round(true + noise, 2)

    async def _drive(self) -> None:
        ticker = _Ticker(self._tick_hz)
        longest_step = 5 * ticker.period  # after a stall, do not jump across the room
        loop = asyncio.get_running_loop()
        while True:
            await self._go.wait()  # an idle robot sleeps here: it changes nothing, sends nothing
            ticker.restart()
            while self._target is not None or self._command is not None:
                # A command ends on time, not at the next tick after it expired.
                left = self.velocity_timeout - self._command_age if self._command is not None else None
                dt = await ticker.wait(None if left is None else loop.time() + max(0.0, left))
                if self._command is not None:
                    # Not capped: the command's own timeout bounds how far it goes.
                    self.advance(dt)
                else:
                    self.advance(min(dt, longest_step))

    def _report_velocity(self, velocity: Vector) -> None:
        self._velocity = velocity
        self.changed("velocity")

    def _standstill(self) -> None:
        if np.any(self._velocity):
            self._report_velocity(np.zeros(6))
            self.actuators.wheels = np.zeros(2)

    def _coast(self, dt: float) -> None:
        """Follow the velocity command for ``dt`` seconds, no longer than it holds."""
        command = self._command
        assert command is not None
        run = min(dt, max(0.0, self.velocity_timeout - self._command_age))
        self._command_age += dt
        if run > 0.0:
            pose = self.location
            new = pose.copy()
            new[:3] += command[:3] * run
            new[5] = math.remainder(pose[5] + command[5] * run, math.tau)
            self._drain(float(np.linalg.norm(command[:3])) * run)
            self.location = new
        if self._command_age >= self.velocity_timeout:
            self.halt()  # not renewed in time: the operator is gone, the robot stops by itself

    def _step(self, dt: float) -> None:
        target = self._target
        assert target is not None
        pose = self.location
        delta = target - pose[:3]
        distance = float(np.linalg.norm(delta))
        step = self.speed * dt
        new = pose.copy()
        if distance <= step:
            new[:3] = target  # arrive exactly: no overshoot, no creeping
            self._target = None
            self._go.clear()
            self._standstill()
            self._drain(distance)
            self.location = new
            return
        if step <= 0.0:
            self._standstill()
            return
        direction = delta / distance
        new[:3] += direction * step
        if math.hypot(delta[0], delta[1]) > 1e-12:
            new[5] = math.atan2(delta[1], delta[0])
        turn = math.remainder(new[5] - pose[5], math.tau)
        velocity = np.zeros(6)
        velocity[:3] = direction * self.speed
        velocity[5] = turn / dt if dt > 0 else 0.0
        self._report_velocity(velocity)
        self.actuators.wheels = np.full(2, self.speed)
        self._drain(step)
        self.location = new

    def _drain(self, metres: float) -> None:
        if metres > 0:
            self._charge = max(0.0, self._charge - metres * BATTERY_PER_METRE)
            # Reported to 1e-4: listeners hear of every 10 cm driven, not of every tick.
            self.sensors.battery = round(self._charge, 4)


class SimSensor(Resource):
    """A simulated temperature sensor: a slow daily-like swing plus seeded Gaussian noise."""

    resource_type = "sensor"

    location: Annotated[
        Vector, Prop(readonly=True, gui="pose", unit="m, rad", length=6, resolution=0.01, doc="sensor pose")
    ]
    data: Annotated[
        float,
        Prop(readonly=True, gui="plot", unit="degC", resolution=0.1, doc="temperature, degrees Celsius"),
    ]

    def __init__(
        self,
        *,
        location: Sequence[float] = (0.0, 0.0),
        rate_hz: float = 5.0,
        seed: int | None = None,
        mean: float = 20.0,
        swing: float = 2.0,
        noise: float = 0.1,
        period_s: float = 600.0,
    ) -> None:
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
            raise InvalidArgument(f"seed must be an integer, got {seed!r}")
        self.location = _pose(location, "location")
        self._rate_hz = _rate(rate_hz, "rate_hz", 0.1, MAX_TICK_HZ)
        self._mean = _rate(mean, "mean", -1e6, 1e6)
        self._swing = _rate(swing, "swing", 0.0, 1e6)
        self._noise = _rate(noise, "noise", 0.0, 1e6)
        self._period = _rate(period_s, "period_s", 1e-3, 1e9)
        self._rng = np.random.default_rng(seed)
        self._t = 0.0
        self._ticker = _Ticker(self._rate_hz)
        self._task: asyncio.Task[None] | None = None
        self.data = self._reading()

    @property
    def rate_hz(self) -> Annotated[float, Prop(minimum=0.1, maximum=MAX_TICK_HZ, unit="Hz", doc="samples/s")]:
        return self._rate_hz

    @rate_hz.setter
    def rate_hz(self, value: float) -> None:
        self._rate_hz = _rate(value, "rate_hz", 0.1, MAX_TICK_HZ)
        self._ticker.set_rate(self._rate_hz)

    def _reading(self) -> float:
        wave = self._swing * math.sin(math.tau * self._t / self._period)
        return round(self._mean + wave + float(self._rng.normal(0.0, self._noise)), 3)

    def sample(self, dt: float) -> None:
        """Advance the simulated time by ``dt`` seconds and take one reading."""
        self._t += dt
        self.data = self._reading()

    async def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="sim-sensor readings")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None

    async def _run(self) -> None:
        self._ticker.restart()
        while True:
            await self._ticker.wait()
            self.sample(self._ticker.period)
