# framing.Encoder.encode compiled by MicroPython's viper and native emitters
# (framing.Encoder(layout, table, emitter="viper" | "native"), chosen like the
# controller's step: App config "emitter").  One call per frame packs the payload,
# computes the CRC-16 (table-driven) and COBS-stuffs the frame: the same bytes as the
# bytecode path of framing.py (tests/test_proto_fastframe.py checks the three agree
# byte for byte).  Under CPython the decorators are no-ops and ptr8/ptr16/ptr32 plain
# indexing (fallback).  The WebAssembly port has no native emitter: import this module
# only when selected.
#
#   n = encode_viper(lut, raw, out, vals, voff, mid, seq)
#     lut   bytearray from make_lut(layout, table): the CRC table (256 native-order
#           uint16), then per id: payload length, field count, field codes (those of
#           codec.Layout), then the length of the vals array the encoder checked
#     raw   the encoder's unstuffed frame (payload at raw[2:]; raw-byte fields as the
#           caller left them); out: the wire bytes (0x00, COBS(...), 0x00)
#     vals  array('i') of field values, read from vals[voff:] (as int32: the encoder
#           passes only the array it checked, whose length is in lut)
#     -> wire length in out, or -1 when mid is unknown, its payload does not fit or its
#        fields are not all inside vals (the caller then takes the bytecode path,
#        which raises as before); raw and out are then untouched

try:
    import micropython
    from micropython import const
except ImportError:
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

_NIDS = const(32)
_MAXF = const(8)
_RAW = const(0x40)
_SIZE = const(0x3F)
_MAX_PAYLOAD = const(8)  # framing: a 12-byte raw frame = id, seq, payload, crc16
# lut layout (byte offsets)
_L_PLEN = const(512)
_L_NF = const(544)
_L_CODES = const(576)
_L_VLEN = const(832)
LUT_SIZE = const(834)  # even: ptr16 views it whole


def make_lut(layout, table):
    # start-up only: the CRC table and the layout's per-id tables in one bytearray
    lut = bytearray(LUT_SIZE)
    for i in range(256):
        c = table[i]
        # native byte order for ptr16 (every target here is little-endian)
        lut[2 * i] = c & 0xFF
        lut[2 * i + 1] = c >> 8
    for m in range(_NIDS):
        lut[_L_PLEN + m] = layout.plen[m]
        lut[_L_NF + m] = layout.nfields[m]
    for k in range(_NIDS * _MAXF):
        lut[_L_CODES + k] = layout.codes[k]
    return lut


def set_vals_len(lut, n):
    # the length of the vals array the encoder checked (capped: fields past 255 fall back)
    lut[_L_VLEN] = n if n < 255 else 255


@micropython.viper
def encode_viper(lut, raw, out, vals, voff: int, mid: int, seq: int) -> int:
    L = ptr8(lut)
    T = ptr16(lut)
    r = ptr8(raw)
    o = ptr8(out)
    if mid < 0 or mid >= _NIDS or voff < 0:
        return -1
    n = int(L[_L_PLEN + mid])
    nf = int(L[_L_NF + mid])
    if n > _MAX_PAYLOAD or voff + nf > int(L[_L_VLEN]):
        return -1
    v = ptr32(vals)
    c = _L_CODES + mid * _MAXF
    ce = c + nf
    k = voff
    j = 2
    while c < ce:
        code = int(L[c])
        size = code & _SIZE
        if (code & _RAW) == 0:
            x = int(v[k])
            r[j] = x & 0xFF
            if size > 1:
                r[j + 1] = (x >> 8) & 0xFF
                if size > 2:
                    r[j + 2] = (x >> 16) & 0xFF
                    r[j + 3] = (x >> 24) & 0xFF
        k += 1
        j += size
        c += 1
    r[0] = mid
    r[1] = seq & 0xFF
    m = n + 2
    crc = 0xFFFF
    i = 0
    while i < m:
        crc = ((crc << 8) & 0xFFFF) ^ int(T[((crc >> 8) ^ int(r[i])) & 0xFF])
        i += 1
    r[m] = crc >> 8
    r[m + 1] = crc & 0xFF
    # COBS stuffing of raw[0:n+4]
    m += 2
    o[0] = 0
    cpos = 1
    code = 1
    p = 2
    i = 0
    while i < m:
        b = int(r[i])
        i += 1
        if b == 0:
            o[cpos] = code
            cpos = p
            p += 1
            code = 1
        else:
            o[p] = b
            p += 1
            code += 1
            if code == 0xFF:
                o[cpos] = code
                cpos = p
                p += 1
                code = 1
    o[cpos] = code
    o[p] = 0
    return p + 1


@micropython.native
def encode_native(lut, raw, out, vals, voff, mid, seq):
    # encode_viper in plain Python (native-compiled): bytes and ints, no pointers
    if mid < 0 or mid >= _NIDS or voff < 0:
        return -1
    n = lut[_L_PLEN + mid]
    nf = lut[_L_NF + mid]
    if n > _MAX_PAYLOAD or voff + nf > lut[_L_VLEN]:
        return -1
    c = _L_CODES + mid * _MAXF
    ce = c + nf
    k = voff
    j = 2
    while c < ce:
        code = lut[c]
        size = code & _SIZE
        if not code & _RAW:
            x = vals[k]
            raw[j] = x & 0xFF
            if size > 1:
                raw[j + 1] = (x >> 8) & 0xFF
                if size > 2:
                    raw[j + 2] = (x >> 16) & 0xFF
                    raw[j + 3] = (x >> 24) & 0xFF
        k += 1
        j += size
        c += 1
    raw[0] = mid
    raw[1] = seq & 0xFF
    m = n + 2
    crc = 0xFFFF
    for i in range(m):
        t = (((crc >> 8) ^ raw[i]) & 0xFF) << 1
        crc = ((crc << 8) & 0xFFFF) ^ (lut[t] | (lut[t + 1] << 8))
    raw[m] = crc >> 8
    raw[m + 1] = crc & 0xFF
    m += 2
    out[0] = 0
    cpos = 1
    code = 1
    p = 2
    for i in range(m):
        b = raw[i]
        if b == 0:
            out[cpos] = code
            cpos = p
            p += 1
            code = 1
        else:
            out[p] = b
            p += 1
            code += 1
            if code == 0xFF:
                out[cpos] = code
                cpos = p
                p += 1
                code = 1
    out[cpos] = code
    out[p] = 0
    return p + 1


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
