# CPython's stand-ins for what MicroPython's native and viper emitters provide, for the
# generated modules (fastpath, fasttick, fastframe, fastcan, fastlink: host/boards/fwgen
# viper.prelude) run by the host's tests and benches: the decorators a no-op, const the
# identity, the pointer casts plain indexing (ptr16 a 16-bit view).  A MicroPython port never
# imports this module: there `import micropython` succeeds and the casts are the emitter's.


class micropython:
    @staticmethod
    def native(f):
        return f

    viper = native


def const(x):
    return x


def ptr8(a):
    return a


def ptr16(a):
    return memoryview(a).cast("H")


def ptr32(a):
    return a
