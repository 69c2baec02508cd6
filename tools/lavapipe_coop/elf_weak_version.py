#!/usr/bin/env python3
"""Marks one version requirement of an ELF64 little-endian shared object as weak.

Usage: elf_weak_version.py FILE VERSION  (e.g. GLIBC_2.38)

The dynamic linker refuses to load an object that requires a symbol version its libraries lack
(`version 'GLIBC_2.38' not found`), unless the requirement carries VER_FLG_WEAK: then it loads,
and each symbol of that version is bound to whichever loaded object defines it with that version
name. tools/lavapipe_coop.sh uses this with a small shim library that defines the few C23/GCC 14
entry points Debian 13's builds of lavapipe and the validation layer need and Debian 12 lacks.
Prints how many requirements it changed; exits 1 when there was none.
"""
import struct
import sys


def main() -> int:
    path, want = sys.argv[1], sys.argv[2].encode()
    b = bytearray(open(path, "rb").read())
    if b[:4] != b"\x7fELF" or b[4] != 2 or b[5] != 1:
        print(f"{path}: not a 64-bit little-endian ELF file", file=sys.stderr)
        return 1
    shoff, = struct.unpack_from("<Q", b, 0x28)
    shentsize, shnum = struct.unpack_from("<HH", b, 0x3A)
    secs = [struct.unpack_from("<IIQQQQIIQQ", b, shoff + i * shentsize) for i in range(shnum)]
    changed = 0
    for sec in secs:
        if sec[1] != 0x6FFFFFFE:  # SHT_GNU_verneed
            continue
        strtab = secs[sec[6]][4]
        off = sec[4]
        while True:
            _, vn_cnt, _, vn_aux, vn_next = struct.unpack_from("<HHIII", b, off)
            aux = off + vn_aux
            for _ in range(vn_cnt):
                _, flags, _, name, nxt = struct.unpack_from("<IHHII", b, aux)
                end = b.index(0, strtab + name)
                if bytes(b[strtab + name:end]) == want:
                    struct.pack_into("<H", b, aux + 4, flags | 2)  # VER_FLG_WEAK
                    changed += 1
                aux += nxt
            if vn_next == 0:
                break
            off += vn_next
    if changed == 0:
        print(f"{path}: no requirement of {want.decode()}", file=sys.stderr)
        return 1
    open(path, "wb").write(b)
    print(f"{path}: {want.decode()} weak ({changed})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
