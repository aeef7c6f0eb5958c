#!/usr/bin/env python3
"""Writes cdr_vectors.txt: OpenRTM-aist data values marshalled by omniORB's
cdrMarshal, in both byte orders, for client/tests/cdr_golden.rs.

Needs omniORBpy and omniidl, e.g. from pip:
    python3 -m venv /tmp/omni && /tmp/omni/bin/pip install cmeel-omniorbpy
    P=/tmp/omni/lib/python3.*/site-packages/cmeel.prefix
    LD_LIBRARY_PATH=$P/lib PATH=$P/bin:$PATH /tmp/omni/bin/python generate_cdr_vectors.py

The IDL below states the layout of the RTC data types this crate
implements (members in OpenRTM's BasicDataType.idl / ExtendedDataTypes.idl
order); each line of the output is `case endian hex`, endian 0 for big,
1 for little. Strings use omniORB's default native charset, ISO 8859-1.
"""

import os
import subprocess
import sys
import tempfile

IDL = """
module RTC {
  struct Time { unsigned long sec; unsigned long nsec; };
  struct TimedDouble { Time tm; double data; };
  struct TimedLong { Time tm; long data; };
  struct TimedString { Time tm; string data; };
  struct TimedDoubleSeq { Time tm; sequence<double> data; };
  struct Point2D { double x; double y; };
  struct Pose2D { Point2D position; double heading; };
  struct TimedPose2D { Time tm; Pose2D data; };
  struct Velocity2D { double vx; double vy; double va; };
  struct TimedVelocity2D { Time tm; Velocity2D data; };
  struct TimedState { Time tm; short data; };
  struct TimedShort { Time tm; short data; };
  struct TimedUShort { Time tm; unsigned short data; };
  struct TimedULong { Time tm; unsigned long data; };
  struct TimedFloat { Time tm; float data; };
  struct TimedChar { Time tm; char data; };
  struct TimedBoolean { Time tm; boolean data; };
  struct TimedOctet { Time tm; octet data; };
  struct TimedShortSeq { Time tm; sequence<short> data; };
  struct TimedLongSeq { Time tm; sequence<long> data; };
  struct TimedUShortSeq { Time tm; sequence<unsigned short> data; };
  struct TimedULongSeq { Time tm; sequence<unsigned long> data; };
  struct TimedFloatSeq { Time tm; sequence<float> data; };
  struct TimedCharSeq { Time tm; sequence<char> data; };
  struct TimedBooleanSeq { Time tm; sequence<boolean> data; };
  struct TimedOctetSeq { Time tm; sequence<octet> data; };
  struct TimedStringSeq { Time tm; sequence<string> data; };
};
"""


def main():
    out_dir = tempfile.mkdtemp()
    idl = os.path.join(out_dir, "rtc_types.idl")
    with open(idl, "w") as f:
        f.write(IDL)
    subprocess.run(["omniidl", "-bpython", "-C" + out_dir, idl], check=True)
    sys.path.insert(0, out_dir)
    import omniORB
    from omniORB import CORBA
    import RTC

    CORBA.ORB_init([], CORBA.ORB_ID)
    tm = RTC.Time(0x01020304, 0x0A0B0C0D)
    cases = [
        ("timed_double", RTC.TimedDouble(tm, 3.25)),
        ("timed_double_negative", RTC.TimedDouble(RTC.Time(1, 2), -1.0e-300)),
        ("timed_long", RTC.TimedLong(tm, -2)),
        ("timed_string", RTC.TimedString(tm, "go")),
        ("timed_string_empty", RTC.TimedString(tm, "")),
        ("timed_string_latin1", RTC.TimedString(tm, "caf\u00e9 \u00c5")),
        ("timed_double_seq", RTC.TimedDoubleSeq(tm, [1.5, -2.0, 1.0e300])),
        ("timed_double_seq_empty", RTC.TimedDoubleSeq(tm, [])),
        ("timed_pose2d", RTC.TimedPose2D(tm, RTC.Pose2D(RTC.Point2D(1.0, 2.0), 0.5))),
        ("timed_velocity2d", RTC.TimedVelocity2D(tm, RTC.Velocity2D(0.1, 0.2, 0.3))),
        ("timed_state", RTC.TimedState(tm, -3)),
        ("timed_short", RTC.TimedShort(tm, -300)),
        ("timed_ushort", RTC.TimedUShort(tm, 65000)),
        ("timed_ulong", RTC.TimedULong(tm, 4000000000)),
        ("timed_float", RTC.TimedFloat(tm, 1.5)),
        ("timed_char", RTC.TimedChar(tm, "A")),
        ("timed_boolean", RTC.TimedBoolean(tm, True)),
        ("timed_octet", RTC.TimedOctet(tm, 0xFE)),
        ("timed_short_seq", RTC.TimedShortSeq(tm, [1, -2, 3])),
        ("timed_long_seq", RTC.TimedLongSeq(tm, [7, -8])),
        ("timed_ushort_seq", RTC.TimedUShortSeq(tm, [1, 65535])),
        ("timed_ulong_seq", RTC.TimedULongSeq(tm, [1, 4294967295])),
        ("timed_float_seq", RTC.TimedFloatSeq(tm, [0.5, -0.25])),
        ("timed_char_seq", RTC.TimedCharSeq(tm, "hi")),
        ("timed_boolean_seq", RTC.TimedBooleanSeq(tm, [True, False, True])),
        ("timed_octet_seq", RTC.TimedOctetSeq(tm, b"\x00\x01\xff")),
        ("timed_string_seq", RTC.TimedStringSeq(tm, ["a", "", "bcd"])),
    ]
    lines = []
    for name, value in cases:
        tc = omniORB.tcInternal.typeCodeFromClassOrRepoId(type(value))
        for endian in (0, 1):
            lines.append(f"{name} {endian} {omniORB.cdrMarshal(tc, value, endian).hex()}")
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "cdr_vectors.txt")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
