# The app's reports to the host: HEARTBEAT, the read-only STATUS values, SENSORS_RAW,
# VERSION, SESSION, STATS_LOOP and TIMING fields (the dispatcher fills its reply arrays with
# them), and the heap sample STATS_LOOP reports.  Allocation-free (the link calls them
# between ticks under the heap lock).  Telemetry (fill_telemetry) stays in firmware/app.py
# next to the step whose estimate it scales.  A part of firmware/app.py's App.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

try:
    from gc import mem_alloc as _mem_alloc, mem_free as _mem_free
except ImportError:  # CPython
    _mem_alloc = None
    _mem_free = None

from . import msgtable as T

_U16 = const(65535)


class Reports:
    def fill_heartbeat(self, arr):
        arr[0] = self.sup.state
        arr[1] = self.sup.faults
        arr[2] = self.boot
        arr[3] = self.epoch & 0xFF
        arr[4] = self.gains_crc & 0xFF
        arr[5] = self.uptime_ms & 0xFFFF

    def status_get(self, k):
        # msgtable STATUS value k (PARAM_GET(STATUS_BASE + k)); allocation-free
        if k == T.S_UPTIME_MS:
            return self.uptime_ms
        if k == T.S_LATE:
            return self.n_late
        ln = self.link
        if k == T.S_LINK_DEFERRED:
            return getattr(ln, "n_deferred", 0)
        if k == T.S_LINK_WAIT_MAX:
            return getattr(ln, "wait_max", 0)
        st = self.store
        if k == T.S_CFG_STATUS:
            return self.cfg_status
        if k == T.S_CFG_SLOT:
            return st.slot if st is not None else -1
        if k == T.S_CFG_SEQ:
            return st.seq if st is not None else 0
        if k == T.S_STARTS:
            return self.starts
        return 0

    def fill_sensors_raw(self, arr):
        # SENSORS_RAW: the ADC as read (from the calibrated counts; clamped at the rails),
        # the encoder counter as read, the unwrapped position
        s = self.sensors
        arr[0] = s.pot_offset + (s.counts if s.adc_sign > 0 else -s.counts)
        arr[1] = s.last
        arr[2] = s.pos

    def fill_version(self, arr):
        # VERSION fields the app knows (the dispatcher adds version and table hashes)
        arr[3] = self.gains_crc
        arr[4] = self.reset_cause

    def fill_session(self, arr):
        # SESSION: the arming token and the whole uptime
        arr[0] = self.epoch
        arr[1] = self.uptime_ms

    def fill_stats(self, arr):
        # STATS_LOOP: worst step and deadline misses since boot, free heap (64 B units) and
        # collections seen (the heap in use fell between two samples) as last sampled (a
        # fresh sample is taken between ticks while the motor is off); allocation-free, and
        # no heap walk in the tick
        tm = self.timing
        w = tm.worst if tm.worst > tm.step_max else tm.step_max
        arr[0] = w if w < _U16 else _U16
        m = tm.misses + tm.overruns
        arr[1] = m if m < _U16 else _U16
        arr[2] = self.heap_free
        arr[3] = self._gc_count & 0xFFFF
        self._heap_due = True

    def fill_timing(self, arr):
        # TIMING fields since the last report, then a new interval starts
        tm = self.timing
        arr[0] = tm.step_min if tm.steps else 0
        arr[1] = tm.step_max
        arr[2] = tm.period_max if tm.period_max < _U16 else _U16
        arr[3] = tm.overruns
        tm.reset()

    def sample_heap(self):
        # the heap statistics STATS_LOOP reports (outside the control tick only: see __init__)
        self._heap_due = False
        if _mem_free is None:
            return
        f = _mem_free() >> 6
        self.heap_free = f if f < _U16 else _U16
        a = _mem_alloc()
        if a < self._alloc_last:
            self._gc_count += 1
        self._alloc_last = a
