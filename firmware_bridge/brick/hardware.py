"""The hardware layer: read the colour sensor, drive the steering motor.

Three adapters with the same two methods: Pybricks on the EV3, ev3dev2 on ev3dev Python, and a
simulated one that drives a world model (``reset(seed)``, ``read_color()``, ``apply(angle, dt)``)
in real time, so the unchanged brick program can run on a PC.
"""

from .compat import ticks_ms, ticks_diff


class PybricksHardware:
    """EV3 with Pybricks MicroPython: reflected light in percent, steering motor to an angle."""

    def __init__(self, sensor_port="S1", motor_port="A", speed=500):
        from pybricks.ev3devices import ColorSensor, Motor
        from pybricks.parameters import Port

        self.sensor = ColorSensor(getattr(Port, sensor_port))
        self.motor = Motor(getattr(Port, motor_port))
        self.speed = speed

    def reset(self, seed):
        """A run starts with the steering centred (``seed`` only matters to a simulated world)."""
        self.steer(0)

    def read_color(self):
        return self.sensor.reflection()

    def steer(self, angle):
        self.motor.run_target(self.speed, angle, wait=False)


class Ev3devHardware:
    """ev3dev Python (python-ev3dev2): the same readings through sysfs."""

    def __init__(self, sensor_port="in1", motor_port="outA", speed=50):
        from ev3dev2.sensor.lego import ColorSensor
        from ev3dev2.motor import MediumMotor, SpeedPercent

        self.sensor = ColorSensor(sensor_port)
        self.motor = MediumMotor(motor_port)
        self.speed = SpeedPercent(speed)

    def reset(self, seed):
        """A run starts with the steering centred (``seed`` only matters to a simulated world)."""
        self.steer(0)

    def read_color(self):
        return self.sensor.reflected_light_intensity

    def steer(self, angle):
        self.motor.on_to_position(self.speed, angle, block=False)


class SimHardware:
    """A world model advanced by the wall-clock time that passed between calls.

    The steering angle set by ``steer`` acts until the next call, as a motor would hold it.
    """

    def __init__(self, world, seed=0, clock_ms=ticks_ms, diff=ticks_diff):
        self.world = world
        self.seed = seed
        self.angle = 0.0
        self._clock = clock_ms
        self._diff = diff
        self._last = clock_ms()

    def reset(self, seed):
        """Each run starts the world afresh, seeded by the simulator's seed and the run id."""
        self.world.reset(self.seed * 65536 + seed)
        self.angle = 0.0
        self._last = self._clock()

    def _advance(self):
        now = self._clock()
        dt = self._diff(now, self._last)
        if dt > 0:
            self.world.apply(self.angle, dt / 1000.0)
            self._last = now

    def read_color(self):
        self._advance()
        return self.world.read_color()

    def steer(self, angle):
        self._advance()
        self.angle = angle
