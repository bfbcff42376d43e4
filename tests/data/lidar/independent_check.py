"""Checks a rewritten strip against its source with an independent reader.

    python independent_check.py SOURCE REWRITTEN

Both files are read with laspy using LASzip (the C++ reference implementation, through the
`laszip` bindings), which shares no code with the Rust `laz` crate that wrote REWRITTEN. Passes
(exit 0, prints "ok N points") when REWRITTEN holds every point of SOURCE with identical record
bytes, the same point format, scales, offsets and (E)VLRs, except the records that describe the
source's compressed layout (LASzip, COPC), which REWRITTEN must not have. Its LAS version may
be higher than the source's (one that can describe its points), up to 1.4.
"""

import sys

import laspy
import numpy as np

LAYOUT_USER_IDS = {"laszip encoded", "copc"}


def read(path):
    with laspy.open(path, laz_backend=laspy.LazBackend.Laszip) as reader:
        return reader.header, reader.read()


def records(vlrs):
    out = []
    for vlr in vlrs or []:
        if vlr.user_id.lower() in LAYOUT_USER_IDS:
            continue
        data = vlr.record_data_bytes() if hasattr(vlr, "record_data_bytes") else bytes(vlr.record_data)
        out.append((vlr.user_id, vlr.record_id, bytes(data)))
    return out


def main(source, rewritten):
    src_header, src = read(source)
    dst_header, dst = read(rewritten)
    problems = []
    if len(dst.points) != len(src.points) or dst_header.point_count != len(src.points):
        problems.append(f"{len(dst.points)} points (header {dst_header.point_count}), source {len(src.points)}")
    if dst_header.point_format.id != src_header.point_format.id:
        problems.append(f"point format {dst_header.point_format.id}, source {src_header.point_format.id}")
    version = lambda h: (h.version.major, h.version.minor)
    if not version(src_header) <= version(dst_header) <= (1, 4):
        problems.append(f"version {dst_header.version}, source {src_header.version}")
    if not (np.array_equal(dst_header.scales, src_header.scales) and np.array_equal(dst_header.offsets, src_header.offsets)):
        problems.append("scales or offsets differ")
    if not problems and src.points.array.tobytes() != dst.points.array.tobytes():
        differing = np.nonzero(src.points.array != dst.points.array)[0]
        problems.append(f"{len(differing)} point records differ, first at index {differing[0] if len(differing) else '?'}")
    for kind, a, b in (("VLRs", src_header.vlrs, dst_header.vlrs), ("EVLRs", src_header.evlrs, dst_header.evlrs)):
        if records(a) != records(b):
            problems.append(f"{kind} differ: {[r[:2] for r in records(b)]}, source {[r[:2] for r in records(a)]}")
    left = [(v.user_id, v.record_id) for v in list(dst_header.vlrs) + list(dst_header.evlrs or [])
            if v.user_id.lower() == "copc"]
    if left:
        problems.append(f"COPC records left over recompressed data: {left}")
    if problems:
        print(f"{rewritten}: " + "; ".join(problems))
        return 1
    print(f"ok {len(dst.points)} points")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
