# Board entry point (the bundle's top-level main.py calls main()): build the Pico HAL
# from firmware/board.py, the app, the UART host link, and run the loop at the loop
# rate.  The motor is switched off whatever happens.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x


from .boot import boot_count  # noqa: F401 - firmware.main.boot_count, as before


def main(link=None, repl_ms=None):
    # One bundle, every use: the robot (the paced control loop, _robot) at boot, and lockstep
    # hardware-in-the-loop (main_hil.HilMain) on the same link, switched by the MODE command
    # while the motor is off -- no reflash.  MODE hil hands the link to HilMain; MODE robot
    # (or a reset) comes back; MODE repl closes the link and returns to the REPL.
    # link: board.LINK when None -- "uart" (UART0, "uart0" too), "usb" (the Pico's USB
    # serial, link_usb.py) or "can" (MCP2515, robot mode only).  repl_ms (USB link only,
    # board.USB_REPL_MS when None): Ctrl-C reaches the REPL for this long after boot, before
    # the link takes the USB serial (the link turns Ctrl-C off: link_usb.py).
    from . import board
    from . import msgtable as T
    from .hal_pico import HalPico

    hal = HalPico(board)
    cause = hal.reset_cause()
    link = link or getattr(board, "LINK", "uart")
    boot = boot_count()
    from .session import seed
    seed0 = seed()  # the arming token's seed: differs at every start (firmware/session.py)
    if link == "usb":
        ms = getattr(board, "USB_REPL_MS", 0) if repl_ms is None else repl_ms
        if ms > 0:
            import time
            time.sleep_ms(ms)  # Ctrl-C now: KeyboardInterrupt, the REPL (motor off since HalPico())
    port = None
    starts = 0
    import time
    t0 = time.ticks_ms()
    try:
        while True:
            # a MODE switch back to the robot starts a new App: the board did not reset (the
            # boot counter and the reset cause stay), its uptime goes on and `starts` counts it
            starts += 1
            mode, port = _robot(board, hal, link, port, boot, cause, starts, seed0 + starts, _uptime_ms(t0))
            while mode == T.MODE_HIL:
                mode = _hil(port, boot, _uptime_ms(t0))
            if mode == T.MODE_REPL:
                return
    finally:
        # (a machine.UART is kept open; CAN: no port)
        if port is not None:
            from .hilport import HilPort
            if isinstance(port, HilPort):
                port.close()


def _port(hal, link):
    # the link's byte stream, made once (when the first app is ready: the link opens with the
    # loop) and kept across mode switches; None: CAN
    if link == "can":
        return None
    if link == "usb":
        from .link_usb import UsbStream
        return UsbStream()
    return hal.uart()


def _uptime_ms(t0):
    # board time since the first control loop of this boot started (t0: its time.ticks_ms()):
    # 0 for it, then carried across MODE switches (HIL and back), so the uptime a host reads
    # never restarts without a reset (ticks_ms wraps at 2**30 ms: ticks_diff exact for 12 days)
    import time
    return time.ticks_diff(time.ticks_ms(), t0) & 0x3FFFFFFF


def _hil(port, boot, uptime=0):
    # MODE hil: lockstep HIL on the robot's link until MODE robot/repl; returns that mode.
    # The motor stays off (the robot loop switched it off; HilHal drives no pin)
    import gc
    from .hilport import HilPort
    from .main_hil import BoardUART, HilMain
    gc.collect()
    m = HilMain(port if isinstance(port, HilPort) else BoardUART(port), config={"boot": boot, "uptime_ms": uptime})
    m.switch = True
    m.run()
    return m.next_mode


def _robot(board, hal, link, port, boot, cause, starts=1, seed=0, uptime=0):
    # The robot: the paced loop until a MODE switch (returns the mode asked for and the port).
    # Safety net around the loop (see docs/firmware.md, "Hardware cut-offs"):
    #  - a hung loop stops feeding the hardware watchdog (board.WDT_MS): the board resets,
    #    its pins fall back to inputs (driver enable pulled low), and the reset-cause marker
    #    App.run left in a WATCHDOG scratch register says RC_WATCHDOG at the next boot;
    #  - an exception escaping the loop: motor and enable off, F_LOOP latched and reported
    #    in one last heartbeat, marker RC_EXCEPTION, board reset;
    #  - Ctrl-C on the REPL (KeyboardInterrupt): motor off, watchdog stopped, no marker,
    #    so the REPL (and mpremote) stays usable.
    # After a watchdog/exception reset the app boots with F_RESET latched (App.reset_cause).
    from . import msgtable as T
    from .app import App
    from .link_serial import ModeSwitch

    try:
        cfg = board.config()
        cfg["boot"] = boot
        # the reset cause of this boot: only the first start after a reset latches F_RESET
        cfg["reset_cause"] = cause if starts == 1 else T.RC_POWER_ON
        cfg["reset_cause_boot"] = cause
        cfg["starts"] = starts
        cfg["seed"] = seed & 0x3FFFFFFF
        cfg["uptime_ms"] = uptime
        app = App(hal, config=cfg)
        # saved parameters and gain table (two copies on the flash filesystem), before the link
        from .store import ConfigStore
        app.attach_store(ConfigStore(getattr(board, "CONFIG_DIR", "")))
        if port is None:
            port = _port(hal, link)
        app.set_link(_link(board, hal, app, link, port))
    except BaseException:
        hal.off()
        raise
    try:
        app.run()
    except ModeSwitch:
        # MODE hil/repl, ACKed with the motor off: the watchdog stops with the loop
        hal.off()
        hal.wdt_stop()
        hal.mark(T.RC_POWER_ON)
        return app.link.mode, port
    except KeyboardInterrupt:
        hal.off()
        hal.wdt_stop()
        hal.mark(T.RC_POWER_ON)
        raise
    except Exception as e:
        hal.off()
        hal.mark(T.RC_EXCEPTION)
        _report(app, e)
        hal.reset()
    finally:
        hal.off()


def _report(app, e):
    # best effort: latch F_LOOP, send one heartbeat, print the traceback, let the UART drain
    import sys
    import time
    try:
        app._loop_fault()
        ln = app.link
        ln.disp.send_heartbeat((ln.pacer.seq + 1) & 0xFF)
    except Exception:
        pass
    sys.print_exception(e)
    time.sleep_ms(5)


def _link(board, hal, app, link=None, port=None):
    # the host link of the board config (board.LINK; `link` overrides it): "uart" -> COBS
    # frames on UART0 (link_serial), "usb" -> the same on the USB serial (port: link_usb),
    # "can" -> an MCP2515 on SPI (link_can, docs/can.md)
    link = link or getattr(board, "LINK", "uart")
    if link == "can":
        from .link_can import CanLink
        return CanLink(hal.can(), app, board.CAN_BITRATE, board.CAN_XTAL_HZ)
    from .link_serial import SerialLink
    return SerialLink(port if port is not None else hal.uart(), app)
