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
# quadrature encoder A/B: two consecutive GPIOs (the PIO program reads pin A and A+1)
ENC_A_PIN = const(2)
ENC_B_PIN = const(3)
# PIO block and state machine used by the encoder
ENC_PIO_SM = const(0)
# H-bridge: PWM (speed) and DIR (direction) inputs, optional enable/nSLEEP (-1: none)
PWM_PIN = const(16)
DIR_PIN = const(17)
EN_PIN = const(18)
PWM_FREQ = const(20000)
# host link: UART0 on GP0 (TX) / GP1 (RX) through a 3.3 V USB-serial adapter
UART_ID = const(0)
UART_TX_PIN = const(0)
UART_RX_PIN = const(1)
UART_BAUD = const(1000000)
UART_RXBUF = const(1024)  # bytes of receive / transmit buffer (rp2 default: 256)
UART_TXBUF = const(512)
LED_PIN = const(25)

# sensor/actuator directions (+1 or -1): flip instead of rewiring when the first
# power-up check (docs/firmware.md) shows a sign the wrong way round
ADC_SIGN = const(1)
ENC_SIGN = const(1)
MOTOR_SIGN = const(1)


def config():
    # App config for this board (called at start-up, not at import)
    return {"adc_sign": ADC_SIGN, "enc_sign": ENC_SIGN}
