# codec.Layout.pack compiled by MicroPython's viper emitter, for the CAN link's frames
# (link_can.CanLink with App config emitter "viper"): the same bytes as the bytecode pack
# (tests/test_firmware_fastcan.py checks they agree for every message of the table).  On a
# predicted real Pico a bytecode pack of a telemetry frame costs ~360 us (its loop runs from a
# cold flash cache), this one a few us.  Under CPython the decorator is a no-op and ptr8/ptr32
# plain indexing.  The WebAssembly port has no native emitter: import only when selected.
#
#   n = pack_viper(codes, nfields, vals, voff, mid, buf, off)
#     codes, nfields  the Layout's bytearrays (field codes, _MAXF per id; field count per id)
#     vals            array('i'); the caller checks voff + nfields[mid] <= len(vals)
#     -> payload bytes written at buf[off:] (raw-byte fields left as the caller put them)
#   n = frame_viper(codes, nfields, vals, voff, mid, q, cid)
#     the same into a link_can transmit slot q (payload at q[6:]) with the 11-bit id cid and the
#     DLC: link_can.CanLink._fill's bytes in the same call

try:
    import micropython
    from micropython import const
except ImportError:
    class micropython:
        @staticmethod
        def viper(f):
            return f

    def const(x):
        return x

    def ptr8(a):
        return a

    def ptr32(a):
        return a

_MAXF = const(8)
_RAW = const(0x40)
_SIZE = const(0x3F)


@micropython.viper
def pack_viper(codes, nfields, vals, voff: int, mid: int, buf, off: int) -> int:
    c8 = ptr8(codes)
    nf = ptr8(nfields)
    v32 = ptr32(vals)
    b = ptr8(buf)
    base = mid * _MAXF
    n = int(nf[mid])
    o0 = off
    k = 0
    while k < n:
        c = int(c8[base + k])
        size = c & _SIZE
        if not (c & _RAW):
            v = int(v32[voff + k])
            b[off] = v & 0xFF
            if size > 1:
                b[off + 1] = (v >> 8) & 0xFF
                if size > 2:
                    b[off + 2] = (v >> 16) & 0xFF
                    b[off + 3] = (v >> 24) & 0xFF
        off += size
        k += 1
    return off - o0


@micropython.viper
def frame_viper(codes, nfields, vals, voff: int, mid: int, q, cid: int) -> int:
    # a whole LOAD TX BUFFER slot q (link_can: q[0] the instruction, set when loaded): the 11-bit
    # id cid in SIDH/SIDL, EID8/EID0 0, DLC, the payload packed at q[6:]; -> payload length
    b = ptr8(q)
    n = int(pack_viper(codes, nfields, vals, voff, mid, q, 6))
    b[1] = (cid >> 3) & 0xFF
    b[2] = (cid & 7) << 5
    b[3] = 0
    b[4] = 0
    b[5] = n
    return n
