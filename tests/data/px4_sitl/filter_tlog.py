"""Copy a .tlog keeping only some message ids (records byte for byte): how the fleet-truth
tlogs in ``fleet_truth/`` were made from the full GCS-link recordings.

    python tests/data/px4_sitl/filter_tlog.py IN.tlog OUT.tlog
"""

from __future__ import annotations

import struct
import sys
from pathlib import Path

#: HEARTBEAT, GPS_RAW_INT, GPS_GLOBAL_ORIGIN, LOCAL_POSITION_NED, GLOBAL_POSITION_INT,
#: HIL_STATE_QUATERNION, ESTIMATOR_STATUS, EXTENDED_SYS_STATE
KEEP = {0, 24, 49, 32, 33, 115, 230, 245}


def main(src: str, dst: str) -> None:
    data = Path(src).read_bytes()
    out = bytearray()
    i = 0
    while i + 8 < len(data):
        (_,) = struct.unpack(">Q", data[i:i + 8])
        j = i + 8
        if data[j] == 0xFD:
            n = 12 + data[j + 1] + (13 if data[j + 2] & 1 else 0)
            msgid = data[j + 7] | (data[j + 8] << 8) | (data[j + 9] << 16)
        else:
            n = 8 + data[j + 1]
            msgid = data[j + 5]
        if msgid in KEEP:
            out += data[i:j + n]
        i = j + n
    Path(dst).write_bytes(bytes(out))


if __name__ == "__main__":
    main(*sys.argv[1:3])
