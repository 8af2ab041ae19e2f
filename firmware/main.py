# Board entry point (the bundle's top-level main.py calls main()): build the Pico HAL
# from firmware/board.py, the app, the UART host link, and run the loop at the loop
# rate.  The motor is switched off whatever happens.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x


def main():
    from . import board
    from .app import App
    from .hal_pico import HalPico
    from .link_serial import SerialLink

    hal = HalPico(board)
    try:
        app = App(hal, config=board.config())
        app.set_link(SerialLink(hal.uart(), app))
        app.run()
    finally:
        hal.off()
