# The HAL contract, declared once: what App (firmware/app.py) calls on a HAL.
#
# Required (every HAL defines them; App binds them in __init__):
#   read_angle_raw() -> ADC counts of the angle potentiometer
#   read_encoder()   -> the 16-bit encoder counter
#   set_motor(duty)  -> duty in -32767..32767
#   ticks_us()       -> the microsecond clock (wraps at 2**30)
# Optional capabilities: None here means the HAL has none; a HAL that has one defines the
# method or sets the attribute (in __init__ when it depends on the board: HalPico).  App
# reads them once in __init__ (never in the tick):
#   ticks_diff_fast, ticks_add_fast  the port's own tick arithmetic (else fixmath's)
#   set_enable(on)      the motor driver's enable output (on: 0 or 1)
#   estop()             True while the e-stop input is pressed
#   set_period(us)      told the control period (HalPico: the enable dead-man's timeout)
#   read_supply_mv()    the motor supply (duty scaled by nominal/measured, F_UNDERVOLT)
#   adc_open            attribute, True while the angle wiper reads open (F_SENSOR)
#   n_sensor            attribute, host frames received (HIL: the sensor-pause check)
#   wdt_start(ms), wdt_feed(), wdt_stop()  the hardware watchdog
#   mark(cause)         leave a reset-cause marker (msgtable RC_*) for the next start
#   guard_timer()       a machine.Timer-like one-shot timer (init(mode, period, tick_hz,
#                       callback), deinit(), ONE_SHOT) whose callback runs in the main thread at
#                       its next bytecode: admit.py's guard over a user hook (made once, by set_user)
# Class attributes only: nothing runs at import.


class Hal:
    ticks_diff_fast = None
    ticks_add_fast = None
    set_enable = None
    estop = None
    set_period = None
    read_supply_mv = None
    adc_open = None
    n_sensor = None
    wdt_start = None
    wdt_feed = None
    wdt_stop = None
    mark = None
    guard_timer = None
