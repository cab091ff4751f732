"""LZF decompression (liblzf's format), for PCL's ``binary_compressed`` PCD files.

A control byte below 32 starts a run of ``ctrl + 1`` literal bytes; any other is a back
reference: length ``(ctrl >> 5) + 2`` (7 extends it by the next byte), distance
``((ctrl & 31) << 8) + next byte + 1`` into the output written so far.
"""

from __future__ import annotations


def lzf_decompress(data: bytes, size: int) -> bytes:
    """The ``size`` bytes ``data`` decompresses to; ValueError when it is not LZF of that
    size (a reference before the start, a run past the end, a different length)."""
    out = bytearray(size)
    i = o = 0
    n = len(data)
    while i < n:
        ctrl = data[i]
        i += 1
        if ctrl < 32:
            length = ctrl + 1
            if i + length > n or o + length > size:
                raise ValueError("literal run past the end")
            out[o : o + length] = data[i : i + length]
            i += length
            o += length
            continue
        length = ctrl >> 5
        if length == 7:
            length += data[i] if i < n else 0
            i += 1
        if i >= n:
            raise ValueError("back reference cut short")
        ref = o - ((ctrl & 31) << 8) - data[i] - 1
        i += 1
        length += 2
        if ref < 0 or o + length > size:
            raise ValueError("back reference out of range")
        if ref + length <= o:
            out[o : o + length] = out[ref : ref + length]
        else:  # overlapping: repeats the last bytes
            for k in range(length):
                out[o + k] = out[ref + k]
        o += length
    if o != size:
        raise ValueError(f"decompressed to {o} bytes, expected {size}")
    return bytes(out)
