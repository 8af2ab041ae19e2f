# The persisted boot counter (HEARTBEAT.boot): one semantics for the board's main and the
# HIL main (1 on the first start), kept out of both so neither imports the other for it.

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
