# Loop timing statistics, measured with the HAL's microsecond ticks (time.ticks_us on a
# board): step execution time (min, max, mean over windows of 1024 steps), period
# between step starts (max) and its jitter (largest |period - nominal|), overruns (a
# step longer than the period, or a period longer than 1.5 nominal).  Allocation-free.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

from .fixmath import ticks_diff

_WINDOW_BITS = const(10)
_WINDOW = const(1024)
_U16 = const(65535)


class Timing:
    def __init__(self, period_us, diff=None):
        # diff: the tick difference to use (None: fixmath.ticks_diff; a board HAL's
        # time.ticks_diff, the same values for its 2**30 clock, costs a third of it)
        self._diff = diff if diff is not None else ticks_diff
        self.period_us = period_us
        self.mean_us = 0
        self.worst = 0  # longest step of the intervals before this one (since boot)
        self.misses = 0  # overruns of the intervals before this one
        self.step_max = 0
        self.overruns = 0
        self.reset()

    def reset(self):
        # start a new statistics interval (after each TIMING report); the since-boot
        # figures (STATS_LOOP) keep what the interval saw
        if self.step_max > self.worst:
            self.worst = self.step_max
        m = self.misses + self.overruns
        self.misses = m if m < _U16 else _U16
        self.step_min = _U16
        self.step_max = 0
        self.period_max = 0
        self.jitter_max = 0
        self.overruns = 0
        self.steps = 0
        self._sum = 0
        self._n = 0
        self.last_us = 0
        self._have_last = False

    def restart(self):
        # the loop paused between ticks on purpose (a heap sample or a save, motor off: App.run):
        # the next step's gap is not a period (not timed, not an overrun)
        self._have_last = False

    def begin(self, t):
        # a step starts at tick t
        if self._have_last:
            per = self._diff(t, self.last_us)
            if per > self.period_max:
                self.period_max = per
            p = self.period_us
            j = per - p
            if j < 0:
                j = -j
            if j > self.jitter_max:
                self.jitter_max = j
            if per > p + (p >> 1) and self.overruns < _U16:
                self.overruns += 1
        self.last_us = t
        self._have_last = True

    def end(self, t0, t1):
        # the step that began at t0 ended at t1; returns its duration (us)
        ex = self._diff(t1, t0)
        if ex < 0:
            ex = 0
        if ex < self.step_min:
            self.step_min = ex
        if ex > self.step_max:
            self.step_max = ex
        if ex > self.period_us and self.overruns < _U16:
            self.overruns += 1
        if self.steps < _U16:
            self.steps += 1
        if ex > _U16:
            ex = _U16
        s = self._sum + ex
        n = self._n + 1
        if n >= _WINDOW:
            self.mean_us = s >> _WINDOW_BITS
            s = 0
            n = 0
        self._sum = s
        self._n = n
        return ex
