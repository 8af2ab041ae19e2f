# The app's persistent configuration (firmware/store.py): the newest valid saved copy at
# start-up (attach_store), SAVE_CONFIG queued by the dispatcher (cmd_save) and run between
# ticks, motor off (service_save: it allocates and waits for flash erases).  A part of
# firmware/app.py's App; never in the control tick.

try:
    from micropython import heap_lock as _heap_lock, heap_unlock as _heap_unlock
except ImportError:  # CPython, or a port without them
    _heap_lock = None
    _heap_unlock = None

from . import msgtable as T
from .supervisor import DISARMED, FAULT, F_CONFIG


class ConfigSave:
    # ---- persistent configuration (firmware/store.py; never in the control tick) ----
    def attach_store(self, store):
        # start-up: the newest valid saved copy replaces the defaults; copies there but none
        # valid -> defaults, F_CONFIG (arming refused until a table is uploaded).  -> status
        # A copy an older firmware saved with another gain-table layout keeps its parameters
        # (the calibration): its table converted (MIGRATED) or dropped for ours (PARAMS_ONLY).
        from .store import CORRUPT, LOADED, MIGRATED, PARAMS_ONLY, upgrade
        self.store = store
        store.n_params = T.N_PARAMS
        store.n_table = self.ctrl.length
        n = self.ctrl.length
        st, params, table = store.load(self._config_check, lambda t: upgrade(t, self.version, n),
                                       self._params_check)
        self.cfg_status = st
        if st == LOADED or st == MIGRATED or st == PARAMS_ONLY:
            if table is not None:
                self._install_table(table, len(table))
            p = self.params
            n = len(params)
            for q in T.PARAMS:
                i = q[0]
                p[i] = params[i] if i < n else q[5]  # an older firmware's copy: the defaults
            self._apply_params()
        elif st == CORRUPT:
            self.config_bad = True
            self.sup.faults |= F_CONFIG
            self.sup.state = FAULT
        return st

    def _params_check(self, params):
        # every saved parameter in range (an older firmware's copy holds fewer)
        n = len(params)
        for q in T.PARAMS:
            if q[0] >= n:
                continue
            v = params[q[0]]
            if v < q[3] or v > q[4]:
                return False
        return True

    def _config_check(self, params, table):
        # a saved copy's content: every parameter in range, the table passes the check
        return self._params_check(params) and self.ctrl.validate(table, len(table), self.version) == T.OK

    def cmd_save(self, disp, seq):
        # SAVE_CONFIG: queue a save of the parameters and the active table; disp.reply()
        # answers it once service_save() has run (App.run: after this tick)
        if self.store is None:
            return T.R_NOT_SUPPORTED
        st = self.sup.state
        if st != DISARMED and st != FAULT:
            return T.R_ARMED
        if self.save_seq >= 0:
            return T.R_BAD_STATE
        self._save_disp = disp
        self.save_seq = seq
        return T.OK

    def service_save(self, locked=False):
        # run a queued save now (outside the control tick: it allocates and may wait for
        # flash erases); locked: the caller holds the heap lock (released meanwhile)
        seq = self.save_seq
        if seq < 0:
            return
        self.save_seq = -1
        st = self.sup.state
        if st != DISARMED and st != FAULT:
            r = T.R_ARMED
        else:
            if locked:
                _heap_unlock()
            try:
                try:
                    self.store.save(self.params, self.table)
                    self.n_saves += 1
                    r = T.OK
                except OSError:
                    r = T.R_STORAGE
            finally:
                if locked:
                    _heap_lock()
        d = self._save_disp
        if d is not None:
            d.reply(T.SAVE_CONFIG, seq, r)
