# Board configuration: the one place that names pins.  Default board: Raspberry Pi Pico
# (RP2040).  Change this file (or copy it) for another board or wiring; the logic
# modules never see a pin.  See docs/firmware.md for the wiring diagram.

try:
    from micropython import const
except ImportError:
    def const(x):
        return x

NAME = "pico"

# angle potentiometer wiper -> ADC0 (GP26); pot ends to 3V3(ADC_VREF, pin 35) and AGND (pin 33)
ADC_PIN = const(26)
# the RP2040 ADC is 12-bit; read_u16() scales it to 16 bits: shift back
ADC_SHIFT = const(4)
# samples averaged per control tick (oversampling: a power of two, 1..16)
ADC_OVERSAMPLE = const(4)
# open-wiper test: every this many ticks one extra sample with the pad pulled toward the far
# rail (0: off).  An open wiper follows the pull; a connected pot (<= 50 kOhm) hardly moves.
# See docs/firmware.md (wiring) -- or fit a 1 MOhm resistor from the wiper to AGND.
ADC_OPEN_TEST_TICKS = const(50)
# motor supply: V+ -> R1 -> GP27 (ADC1) -> R2 -> AGND, V = adc * ADC_VREF_MV / 4095 * NUM / DEN
# (default R1 = 100k, R2 = 10k: 36 V full scale); -1: not measured (duty for the nominal supply)
VSUP_ADC_PIN = const(27)
VSUP_DIV_NUM = const(110)
VSUP_DIV_DEN = const(10)
ADC_VREF_MV = const(3300)
# the supply the gain table's motor constants assume (robot.toml motor.V_supply) and the
# undervoltage threshold (F_UNDERVOLT while armed/balancing)
VSUP_NOMINAL_MV = const(12000)
VSUP_MIN_MV = const(9000)
# quadrature encoder A/B: two consecutive GPIOs (the PIO program reads pin A and A+1)
ENC_A_PIN = const(2)
ENC_B_PIN = const(3)
# PIO block and state machine used by the encoder
ENC_PIO_SM = const(0)
# H-bridge: PWM (speed) and DIR (direction) inputs, optional enable/nSLEEP (-1: none)
PWM_PIN = const(16)
DIR_PIN = const(17)
EN_PIN = const(18)
# driver-enable dead-man: EN is driven by a PIO state machine (PIO1's machine DEADMAN_SM - 4;
# the encoder's program fills PIO0) that holds it low unless the control loop refreshes it
# (set_motor, every tick): the driver is cut DEADMAN_PCT % of a loop period after the last
# refresh, whatever the CPU is doing (a hang anywhere, interrupts off); the hardware watchdog
# resets the board later.  175: 3.5 ms at 500 Hz -- a tick may start 0.75 period late (the
# late-tick rule counts 0.5), and a hang anywhere in a tick cuts within 3 periods of the last
# complete one.  -1: no dead-man (EN a plain output).  docs/firmware.md, "Hardware cut-offs"
DEADMAN_SM = const(4)
DEADMAN_PCT = const(175)
# e-stop input: a normally-closed switch to GND (active low, internal pull-up; -1: none).
# Asserted -> motor and enable off at once (pin IRQ), F_ESTOP latched (docs/firmware.md)
ESTOP_PIN = const(19)
# hardware watchdog (machine.WDT) fed only by the control loop: a loop stuck this long
# resets the board (pins back to inputs: fit a pull-down on EN so the driver is off)
WDT_MS = const(100)
PWM_FREQ = const(20000)
# host link: UART0 on GP0 (TX) / GP1 (RX) through a 3.3 V USB-serial adapter
UART_ID = const(0)
UART_TX_PIN = const(0)
UART_RX_PIN = const(1)
UART_BAUD = const(1000000)
UART_RXBUF = const(1024)  # bytes of receive / transmit buffer (rp2 default: 256)
UART_TXBUF = const(512)
LED_PIN = const(25)
# how the hot code is compiled (App config "emitter": the controller step, the telemetry
# scaling and the frame encoder): "viper" is the fastest that is right on the RP2040
# (tests/test_firmware_fastpath.py, tests/test_proto_fastframe.py); "bytecode" runs anywhere
EMITTER = "viper"
# host link: "uart" (UART0 above, through a USB-serial adapter: /dev/ttyUSB0), "usb" (the
# Pico's own USB serial, /dev/ttyACM0, at any baud: the REPL's port, see firmware/link_usb.py
# for the way back to the REPL) or "can" (an MCP2515 module on SPI1, docs/can.md).  The same
# bundle runs the robot and serves HIL on this link (the MODE command, firmware/main.py)
LINK = "uart"
# USB link: Ctrl-C (mpremote) reaches the REPL for this long after a reset, before the link
# takes the USB serial
USB_REPL_MS = const(2000)
# MCP2515 on SPI1: SCK GP10, MOSI (SI) GP11, MISO (SO) GP12, CS GP13, INT GP14 (active low,
# pulled up here); SPI clock <= 10 MHz (the chip's maximum).  The module's crystal (8 or
# 16 MHz, printed on the can) and the bus bit rate (500 kbit/s or 1 Mbit/s; 1 Mbit/s needs
# 16 MHz); the node id is the node_id parameter (CAN id = node_id << 5 | msg_id)
CAN_SPI_ID = const(1)
CAN_SCK_PIN = const(10)
CAN_MOSI_PIN = const(11)
CAN_MISO_PIN = const(12)
CAN_CS_PIN = const(13)
CAN_INT_PIN = const(14)
CAN_SPI_HZ = const(10000000)
CAN_XTAL_HZ = const(16000000)
CAN_BITRATE = const(500000)

# sensor/actuator directions (+1 or -1): flip instead of rewiring when the first
# power-up check (docs/firmware.md) shows a sign the wrong way round
ADC_SIGN = const(1)
ENC_SIGN = const(1)
MOTOR_SIGN = const(1)


def config():
    # App config for this board (called at start-up, not at import)
    return {"adc_sign": ADC_SIGN, "enc_sign": ENC_SIGN, "vsup_nom_mv": VSUP_NOMINAL_MV, "vsup_min_mv": VSUP_MIN_MV,
            "wdt_ms": WDT_MS, "emitter": EMITTER}
