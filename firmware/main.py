# Board entry point (the bundle's top-level main.py calls main()): build the Pico HAL
# from firmware/board.py, the app, the UART host link, and run the loop at the loop
# rate.  The motor is switched off whatever happens.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x


_BOOT_FILE = "boot_count"


def boot_count(path=_BOOT_FILE):
    # increment and return the persisted boot counter (mod 256) for HEARTBEAT.boot, so
    # the host sees a reset; one small flash write per start-up
    n = 0
    try:
        with open(path) as f:
            n = int(f.read())
    except (OSError, ValueError):
        n = 0
    n = (n + 1) & 0xFF
    try:
        with open(path, "w") as f:
            f.write(str(n))
    except OSError:
        pass
    return n


def main():
    from . import board
    from .app import App
    from .hal_pico import HalPico
    from .link_serial import SerialLink

    hal = HalPico(board)
    try:
        cfg = board.config()
        cfg["boot"] = boot_count()
        app = App(hal, config=cfg)
        app.set_link(SerialLink(hal.uart(), app))
        app.run()
    finally:
        hal.off()
