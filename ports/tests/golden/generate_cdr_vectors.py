#!/usr/bin/env python3
"""Writes cdr_vectors.txt: OpenRTM-aist data values marshalled by omniORB's
cdrMarshal, in both byte orders, for ports/tests/cdr_golden.rs.

Needs omniORBpy and omniidl, e.g. from pip:
    python3 -m venv /tmp/omni && /tmp/omni/bin/pip install cmeel-omniorbpy
    P=/tmp/omni/lib/python3.*/site-packages/cmeel.prefix
    LD_LIBRARY_PATH=$P/lib PATH=$P/bin:$PATH /tmp/omni/bin/python generate_cdr_vectors.py

The IDL below states the layout of the RTC data types this crate
implements (members in OpenRTM's BasicDataType.idl / ExtendedDataTypes.idl
order); each line of the output is `case endian hex`, endian 0 for big,
1 for little. Strings use omniORB's default native charset, ISO 8859-1.
omniORB leaves alignment padding uninitialised, so padding bytes change
from run to run (the test treats them as don't-care).

Wide characters: a cdrMemoryStream takes omniORB's "any" code sets, which
ORB_init sets from the native ones (ISO 8859-1 and UTF-16, GIOP 1.2);
before ORB_init there is no wide code set (cdrMarshal raises
BAD_INV_ORDER). OpenRTM-aist marshals data port values that way after
its manager's ORB_init, in C++ (CORBA_CdrMemoryStream: a plain
cdrMemoryStream, setByteSwapFlag, `data >>= cdr`) and in Python
(CORBA_CdrMemoryStream.py: cdrMarshal), so the wide cases below are
cdrMarshal's too. omniORB writes a wchar as 2 then the code unit
big-endian, and a wstring's code units in the host's byte order after a
byte order mark saying so: on this (little-endian) host FF FE and
little-endian units in both stream byte orders. The script also marshals
the wide cases the C++ way, with openrtm_cxx_wide.cc built against the
same omniORB (needs g++; the prefix is found from omniidl's path), and
stops unless both give the same bytes, padding aside.
"""

import os
import shutil
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
  struct TimedWChar { Time tm; wchar data; };
  struct TimedWString { Time tm; wstring data; };
  struct TimedWCharSeq { Time tm; sequence<wchar> data; };
  struct TimedWStringSeq { Time tm; sequence<wstring> data; };

  // ExtendedDataTypes.idl, all of it, in its order (Point2D, Pose2D,
  // Velocity2D and their Timed* forms are above).
  struct RGBColour { double r; double g; double b; };
  struct Vector2D { double x; double y; };
  struct Acceleration2D { double ax; double ay; };
  struct PoseVel2D { Pose2D pose; Velocity2D velocities; };
  struct Size2D { double l; double w; };
  struct Geometry2D { Pose2D pose; Size2D size; };
  struct Covariance2D { double xx; double xy; double xt; double yy; double yt; double tt; };
  struct PointCovariance2D { double xx; double xy; double yy; };
  struct Carlike { double speed; double steeringAngle; };
  struct SpeedHeading2D { double speed; double heading; };
  struct Point3D { double x; double y; double z; };
  struct Vector3D { double x; double y; double z; };
  struct Orientation3D { double r; double p; double y; };
  struct Pose3D { Point3D position; Orientation3D orientation; };
  struct Velocity3D { double vx; double vy; double vz; double vr; double vp; double va; };
  struct AngularVelocity3D { double avx; double avy; double avz; };
  struct Acceleration3D { double ax; double ay; double az; };
  struct AngularAcceleration3D { double aax; double aay; double aaz; };
  struct PoseVel3D { Pose3D pose; Velocity3D velocities; };
  struct Size3D { double l; double w; double h; };
  struct Geometry3D { Pose3D pose; Size3D size; };
  struct Covariance3D {
    double xx; double xy; double xz; double xr; double xp; double xa;
    double yy; double yz; double yr; double yp; double ya;
    double zz; double zr; double zp; double za;
    double rr; double rp; double ra;
    double pp; double pa;
    double aa;
  };
  struct SpeedHeading3D { double speed; Orientation3D direction; };
  struct OAP { Vector3D orientation; Vector3D approach; Vector3D position; };
  struct TimedRGBColour { Time tm; RGBColour data; };
  struct TimedPoint2D { Time tm; Point2D data; };
  struct TimedVector2D { Time tm; Vector2D data; };
  struct TimedAcceleration2D { Time tm; Acceleration2D data; };
  struct TimedPoseVel2D { Time tm; PoseVel2D data; };
  struct TimedSize2D { Time tm; Size2D data; };
  struct TimedGeometry2D { Time tm; Geometry2D data; };
  struct TimedCovariance2D { Time tm; Covariance2D data; };
  struct TimedPointCovariance2D { Time tm; PointCovariance2D data; };
  struct TimedCarlike { Time tm; Carlike data; };
  struct TimedSpeedHeading2D { Time tm; SpeedHeading2D data; };
  struct TimedPoint3D { Time tm; Point3D data; };
  struct TimedVector3D { Time tm; Vector3D data; };
  struct TimedOrientation3D { Time tm; Orientation3D data; };
  struct TimedPose3D { Time tm; Pose3D data; };
  struct TimedVelocity3D { Time tm; Velocity3D data; };
  struct TimedAngularVelocity3D { Time tm; AngularVelocity3D data; };
  struct TimedAcceleration3D { Time tm; Acceleration3D data; };
  struct TimedAngularAcceleration3D { Time tm; AngularAcceleration3D data; };
  struct TimedPoseVel3D { Time tm; PoseVel3D data; };
  struct TimedSize3D { Time tm; Size3D data; };
  struct TimedGeometry3D { Time tm; Geometry3D data; };
  struct TimedCovariance3D { Time tm; Covariance3D data; };
  struct TimedSpeedHeading3D { Time tm; SpeedHeading3D data; };
  struct TimedOAP { Time tm; OAP data; };
  struct Quaternion { double x; double y; double z; double w; };
  struct TimedQuaternion { Time tm; Quaternion data; };
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
    wide = wide_cases(RTC, tm)
    cases += wide
    cases += extended_cases(RTC, tm)
    lines = []
    for name, value in cases:
        tc = omniORB.tcInternal.typeCodeFromClassOrRepoId(type(value))
        for endian in (0, 1):
            lines.append(f"{name} {endian} {omniORB.cdrMarshal(tc, value, endian).hex()}")
    check_wide_against_cxx(out_dir, idl, lines, [name for name, _ in wide])
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "cdr_vectors.txt")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def wide_cases(RTC, tm):
    """The wide-character types of BasicDataType.idl: characters whose
    UTF-16 bytes differ (so a byte order cannot go unseen), one beyond
    U+FFFF (a surrogate pair), a string starting with U+FEFF (a character,
    not a byte order mark), and padding between the strings of a
    sequence. openrtm_cxx_wide.cc marshals the same values; cdr_golden.rs
    builds them too."""
    return [
        ("timed_wchar", RTC.TimedWChar(tm, "\u03a9")),
        ("timed_wchar_ascii", RTC.TimedWChar(tm, "A")),
        ("timed_wstring", RTC.TimedWString(tm, "A\u00e9\u20ac")),
        ("timed_wstring_empty", RTC.TimedWString(tm, "")),
        ("timed_wstring_surrogates", RTC.TimedWString(tm, "x\U0001f600")),
        ("timed_wstring_feff", RTC.TimedWString(tm, "\ufeffA")),
        ("timed_wchar_seq", RTC.TimedWCharSeq(tm, ["a", "\u03a9", "\u20ac"])),
        ("timed_wchar_seq_empty", RTC.TimedWCharSeq(tm, [])),
        (
            "timed_wstring_seq",
            RTC.TimedWStringSeq(tm, ["a", "", "\u03a9\u03bc", "x\U0001f600"]),
        ),
    ]


def check_wide_against_cxx(out_dir, idl, lines, names):
    """Marshals the wide cases as OpenRTM-aist's C++ does and stops unless
    every byte is cdrMarshal's, but where the C++ stream's is zero (its
    buffer is cleared, so its padding is zero; cdrMarshal's padding is
    whatever was in memory)."""
    prefix = os.path.dirname(os.path.dirname(os.path.realpath(shutil.which("omniidl"))))
    subprocess.run(["omniidl", "-bcxx", "-C" + out_dir, idl], check=True)
    binary = os.path.join(out_dir, "openrtm_cxx_wide")
    source = os.path.join(os.path.dirname(os.path.abspath(__file__)), "openrtm_cxx_wide.cc")
    subprocess.run(
        ["g++", "-O1", "-I" + os.path.join(prefix, "include"), "-I" + out_dir,
         source, os.path.join(out_dir, "rtc_typesSK.cc"),
         "-L" + os.path.join(prefix, "lib"), "-Wl,-rpath," + os.path.join(prefix, "lib"),
         "-lomniORB4", "-lomnithread", "-o", binary],
        check=True,
    )
    cxx = subprocess.run([binary], check=True, capture_output=True, text=True).stdout
    ours = {tuple(line.split()[:2]): bytes.fromhex(line.split()[2]) for line in lines}
    checked = set()
    for line in cxx.splitlines():
        name, endian, data = line.split()
        theirs = bytes.fromhex(data)
        py = ours[(name, endian)]
        if len(py) != len(theirs) or any(a != b and b != 0 for a, b in zip(py, theirs)):
            sys.exit(f"{name} {endian}: C++ {data}, cdrMarshal {py.hex()}")
        checked.add((name, endian))
    if checked != {(name, endian) for name in names for endian in "01"}:
        sys.exit(f"the C++ program marshalled {sorted(checked)}, not every wide case")
    print(f"{len(checked)} wide vectors: C++ cdrMemoryStream and cdrMarshal agree")


def extended_cases(RTC, tm):
    """One case per ExtendedDataTypes.idl type, named as the type: within
    a value every double differs (a member read in the wrong place cannot
    go unseen); cdr_golden.rs builds the same values."""
    point2d = RTC.Point2D(x=1.1, y=-1.2)
    pose2d = RTC.Pose2D(position=point2d, heading=1.3)
    velocity2d = RTC.Velocity2D(vx=3.1, vy=-3.2, va=3.3)
    size2d = RTC.Size2D(l=5.1, w=5.2)
    point3d = RTC.Point3D(x=11.1, y=-11.2, z=11.3)
    vector3d = RTC.Vector3D(x=12.1, y=-12.2, z=12.3)
    orientation3d = RTC.Orientation3D(r=13.1, p=-13.2, y=13.3)
    pose3d = RTC.Pose3D(position=point3d, orientation=orientation3d)
    velocity3d = RTC.Velocity3D(vx=14.1, vy=-14.2, vz=14.3, vr=-14.4, vp=14.5, va=-14.6)
    size3d = RTC.Size3D(l=18.1, w=18.2, h=18.3)
    members = "xx xy xz xr xp xa yy yz yr yp ya zz zr zp za rr rp ra pp pa aa".split()
    covariance3d = RTC.Covariance3D(
        **{m: float(f"{'-' if i % 2 else ''}19.{i + 1:02}") for i, m in enumerate(members)}
    )
    values = [
        RTC.RGBColour(r=0.1, g=0.6, b=0.9),
        point2d,
        RTC.Vector2D(x=2.1, y=-2.2),
        pose2d,
        velocity2d,
        RTC.Acceleration2D(ax=4.1, ay=-4.2),
        RTC.PoseVel2D(pose=pose2d, velocities=velocity2d),
        size2d,
        RTC.Geometry2D(pose=pose2d, size=size2d),
        RTC.Covariance2D(xx=6.1, xy=-6.2, xt=6.3, yy=-6.4, yt=6.5, tt=-6.6),
        RTC.PointCovariance2D(xx=7.1, xy=-7.2, yy=7.3),
        RTC.Carlike(speed=8.1, steeringAngle=-8.2),
        RTC.SpeedHeading2D(speed=9.1, heading=-9.2),
        point3d,
        vector3d,
        orientation3d,
        pose3d,
        velocity3d,
        RTC.AngularVelocity3D(avx=15.1, avy=-15.2, avz=15.3),
        RTC.Acceleration3D(ax=16.1, ay=-16.2, az=16.3),
        RTC.AngularAcceleration3D(aax=17.1, aay=-17.2, aaz=17.3),
        RTC.PoseVel3D(pose=pose3d, velocities=velocity3d),
        size3d,
        RTC.Geometry3D(pose=pose3d, size=size3d),
        covariance3d,
        RTC.SpeedHeading3D(speed=20.1, direction=orientation3d),
        RTC.OAP(
            orientation=vector3d,
            approach=RTC.Vector3D(x=21.1, y=-21.2, z=21.3),
            position=RTC.Vector3D(x=22.1, y=-22.2, z=22.3),
        ),
        RTC.Quaternion(x=23.1, y=-23.2, z=23.3, w=-23.4),
    ]
    cases = []
    for value in values:
        name = type(value).__name__
        cases.append((name, value))
        cases.append(("Timed" + name, getattr(RTC, "Timed" + name)(tm, value)))
    return cases


if __name__ == "__main__":
    main()
