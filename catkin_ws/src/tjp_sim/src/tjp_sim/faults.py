"""Software-implemented fault injection on the car's sensors (second paper, section III.D: SWIFI
of transient IMU and laser faults), without rospy.

A scenario declares the faults (:mod:`tjp_sim.scenario`); the simulator passes every reading
through :meth:`SensorFaults.apply` before publishing it. Kinds of value fault, each active from
``at`` until ``until`` (sim seconds):

- ``stuck``: the sensor reads ``value`` whatever is there;
- ``offset``: the reading is off by ``offset``;
- ``noise``: a noise burst, Gaussian of standard deviation ``sigma``;
- ``spikes``: each reading, with ``probability``, jumps by ``magnitude``, in a random ``direction``
  (both, the default) or always ``up`` or ``down`` (a dropout towards zero);
- ``false_detection``: the ultrasonic sees an obstacle at ``distance`` that is not there;
- ``crash``: the sensor falls silent for good (``until`` does not apply).

Random draws come from one generator per sensor seeded from the scenario's seed, so a run with
the same seed injects the same faults whatever the other sensors do.
"""
import math
import random

VALUE_KINDS = ('stuck', 'offset', 'noise', 'spikes', 'false_detection')
SILENT = object()   # apply() result: the sensor publishes nothing


class SensorFaults(object):
    """The value faults and crashes of a scenario; counts what it injected per sensor."""

    def __init__(self, faults, seed):
        self.faults = [f for f in faults if f['kind'] in VALUE_KINDS + ('crash',)]
        self.rngs = {}
        self.seed = seed
        self.injected = {}    # sensor -> readings altered or suppressed

    def _rng(self, sensor):
        if sensor not in self.rngs:
            self.rngs[sensor] = random.Random('%d/%s' % (self.seed, sensor))
        return self.rngs[sensor]

    def active(self, sensor, t):
        """The faults of sensor active at t."""
        return [f for f in self.faults if f['sensor'] == sensor and f['at'] <= t and
                (f['kind'] == 'crash' or t < f['until'])]

    def apply(self, sensor, t, value):
        """The reading the sensor gives at t for the true value (None: nothing in range).
        Returns (reading, faulty) where reading may be SILENT (the sensor crashed)."""
        faults = self.active(sensor, t)
        if not faults:
            return value, False
        rng = self._rng(sensor)
        reading, faulty = value, False
        for fault in faults:
            kind = fault['kind']
            if kind == 'crash':
                reading, faulty = SILENT, True
                break
            if kind == 'false_detection':
                reading, faulty = fault['distance'], True
            elif kind == 'stuck':   # whatever is there, or nothing (review of session 34: nothing in range
                reading, faulty = fault['value'], True   # read nothing, the phantom obstacle never came)
            elif reading is None:
                continue    # nothing in range: a value fault has nothing to alter
            elif kind == 'offset':
                reading, faulty = reading + fault['offset'], True
            elif kind == 'noise':
                reading, faulty = reading + rng.gauss(0.0, fault['sigma']), True
            elif kind == 'spikes' and rng.random() < fault['probability']:
                sign = {'up': 1.0, 'down': -1.0}.get(fault.get('direction', 'both')) or rng.choice((-1.0, 1.0))
                reading, faulty = reading + sign * fault['magnitude'], True
        if faulty and reading is not SILENT and reading is not None and math.isfinite(reading):
            # A range or a speed is never negative. NaN and infinities go as given (REP 117's invalid
            # readings): max(0.0, nan) made a scenario's NaN an obstacle at 0 m (review of session 34).
            reading = max(0.0, reading)
        if faulty:
            self.injected[sensor] = self.injected.get(sensor, 0) + 1
        return reading, faulty
