# Viper builds of two link-side per-tick helpers, still written by hand (the frame encoder
# that used to sit beside them is generated now: fastframe.py).  firmware/emitter.py imports
# this module only for the viper emitter (the WebAssembly port has no native emitter).
#   telem_viper   App.fill_telemetry's six scaled fields in one call (App._tel per field)
#   crc32_low30   commands.Dispatcher's integrity check (crc32.Crc32 over mid and a payload)
# tests/test_proto_fastframe.py compares telem_viper with the plain scaling under the unix
# port's viper; crc32_low30 runs on every viper link (link_serial, main_hil: a wrong CRC would
# refuse every checked command).  Under CPython the decorator is a no-op and
# ptr8/ptr16/ptr32 plain indexing (fallback).

try:
    import micropython
except ImportError:
    class micropython:
        @staticmethod
        def viper(f):
            return f

    def ptr8(a):
        return a

    def ptr16(a):
        return a

    def ptr32(a):
        return a


@micropython.viper
def telem_viper(arr, t, xf, o: int, vh: int, ref: int, u: int) -> int:
    # App.fill_telemetry's scaled fields: arr[0:6] = x, xdot, phi, phidot (xf[0], vh,
    # xf[2], xf[3]), ref, force (u), each (v * TEL[j] + 2**(S-1)) >> S clamped to
    # +-32767 (t: the gain table, TEL at t[o:o+6], S = t[o+5]; every product stays
    # inside +-2**30: host/design/export.py proves it).  t and xf: array('i'), read as
    # int32 (sign-extended on 64-bit ports as fastpath.py does); arr: any int sequence
    tb = ptr32(t)
    x = ptr32(xf)
    sb = 1
    sb = sb << 31
    msk = sb | (sb - 1)
    s = ((int(tb[o + 5]) + sb) & msk) - sb
    h = 1 << (s - 1)
    j = 0
    while j < 6:
        if j == 0:
            v = ((int(x[0]) + sb) & msk) - sb
            g = tb[o]
        elif j == 1:
            v = vh
            g = tb[o + 1]
        elif j == 2:
            v = ((int(x[2]) + sb) & msk) - sb
            g = tb[o + 2]
        elif j == 3:
            v = ((int(x[3]) + sb) & msk) - sb
            g = tb[o + 3]
        elif j == 4:
            v = ref
            g = tb[o]
        else:
            v = u
            g = tb[o + 4]
        v = (v * (((int(g) + sb) & msk) - sb) + h) >> s
        if v > 32767:
            v = 32767
        elif v < -32767:
            v = -32767
        arr[j] = v
        j += 1
    return 6


@micropython.viper
def crc32_low30(th: ptr16, tl: ptr16, mid: int, buf: ptr8, off: int, n: int) -> int:
    # CRC-32/ISO-HDLC of the byte mid and buf[off:off+n], its low 30 bits (commands.Dispatcher's
    # integrity check, crc32.Crc32 written out in viper: the 16-bit halves of the register and of
    # the table th/tl; every value < 2**16, the result a small int)
    k = (0xFF ^ mid) & 0xFF
    lo = 0xFFFF ^ int(tl[k])
    hi = 0xFF ^ int(th[k])
    i = off
    end = off + n
    while i < end:
        k = (lo ^ int(buf[i])) & 0xFF
        lo = ((lo >> 8) | ((hi & 0xFF) << 8)) ^ int(tl[k])
        hi = (hi >> 8) ^ int(th[k])
        i += 1
    lo = lo ^ 0xFFFF
    hi = hi ^ 0xFFFF
    return ((hi & 0x3FFF) << 16) | lo
