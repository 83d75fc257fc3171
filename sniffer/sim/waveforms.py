"""Simulated sensor readings: a shape per channel that a person recognises on a plot.

Each reading is a pure function of (seed, channel, time), so a test that pins the
clock knows every value in advance and two runs with one seed agree.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass
from functools import lru_cache

from whiztap.analyzer.protocol.codec import MAX_SENSOR_DATA

SHAPES = ("sine", "ramp", "noise")
_NOISE_POINTS = 256  # the noise repeats after this many steps
_NOISE_STEP_S = 0.5


def _clamp(value: float) -> int:
    return max(0, min(MAX_SENSOR_DATA, round(value)))


@dataclass(frozen=True, slots=True)
class Sine:
    period_s: float
    amplitude: float
    offset: float
    phase: float

    def value(self, t_s: float) -> int:
        return _clamp(self.offset + self.amplitude * math.sin(2 * math.pi * t_s / self.period_s + self.phase))


@dataclass(frozen=True, slots=True)
class Ramp:
    """A sawtooth: climbs from low to high over a period, then drops back."""

    period_s: float
    low: float
    high: float

    def value(self, t_s: float) -> int:
        return _clamp(self.low + (self.high - self.low) * ((t_s / self.period_s) % 1.0))


@dataclass(frozen=True, slots=True)
class Noise:
    """A random walk sampled every half second, linearly interpolated: wanders, never jumps."""

    points: tuple[float, ...]

    def value(self, t_s: float) -> int:
        x = t_s / _NOISE_STEP_S
        i = math.floor(x)
        a = self.points[i % _NOISE_POINTS]
        b = self.points[(i + 1) % _NOISE_POINTS]
        return _clamp(a + (b - a) * (x - i))


Signal = Sine | Ramp | Noise


def _noise(rng: random.Random) -> Noise:
    level = rng.uniform(300, 700)
    points = []
    for _ in range(_NOISE_POINTS):
        level = min(MAX_SENSOR_DATA - 50, max(50, level + rng.gauss(0, 40)))
        points.append(level)
    return Noise(tuple(points))


@lru_cache(maxsize=256)  # signals are immutable; every Robot of a test run asks for the same ones
def make_signal(seed: int, channel: int) -> Signal:
    """The signal of one sensor channel, chosen and shaped by the seed."""
    rng = random.Random(f"whiztap-sensor:{seed}:{channel}")
    shape = rng.choice(SHAPES)
    if shape == "sine":
        return Sine(rng.uniform(4, 20), rng.uniform(150, 500), rng.uniform(400, 620), rng.uniform(0, 2 * math.pi))
    if shape == "ramp":
        low = rng.uniform(0, 200)
        return Ramp(rng.uniform(5, 30), low, rng.uniform(low + 400, MAX_SENSOR_DATA))
    return _noise(rng)
