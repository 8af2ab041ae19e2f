# The byte stream the host link runs on in HIL mode (main_hil.HilMain) and the board's
# robot-mode streams that also serve HIL (main.py): its surface declared once, so that
# nothing probes a port for what it offers.
#
#   wait(timeout_ms) -> bool   bytes came within timeout_ms (0: poll)
#   any() -> int               bytes waiting (a port may say 1 when there are more)
#   readinto(buf, n) -> int    read at most n of what any()/wait() reported
#   write(buf, n) -> int       write buf[:n] (allocation-free after the first call)
#   hup                        the far end hung up (a closed pty: uart_unix.UnixUART); False
#                              on a board, whose UART has no far end to lose
#   close()                    release it (nothing to do on a board's UART)
#
# Subclasses: uart_unix.UnixUART (the unix port's pty), main_hil.BoardUART (machine.UART),
# link_usb.UsbStream (the Pico's USB serial).  A machine.UART itself is not one: main_hil and
# main.py wrap it in a BoardUART.


class HilPort:
    hup = False

    def close(self):
        pass
