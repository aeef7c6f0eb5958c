#!/usr/bin/env python3
"""Writes interface_vectors.txt: values of OpenRTM-aist's
InterfaceDataTypes.idl types marshalled by omniORB's cdrMarshal, in both
byte orders, for ports/tests/cdr_golden.rs.

The IDL is OpenRTM-aist's own, read from a checkout of it (not copied
here): python3 generate_interface_vectors.py OPENRTM_CHECKOUT, where the
checkout has src/lib/rtm/idl/{BasicDataType,ExtendedDataTypes,
InterfaceDataTypes}.idl (n-ando/OpenRTM-aist; the commit used is written
on the file's first line). Needs omniORBpy and omniidl, e.g. from pip:
    python3 -m venv /tmp/omni && /tmp/omni/bin/pip install cmeel-omniorbpy
    P=/tmp/omni/lib/python3.*/site-packages/cmeel.prefix
    LD_LIBRARY_PATH=$P/lib PATH=$P/bin:$PATH /tmp/omni/bin/python \
        generate_interface_vectors.py OPENRTM_CHECKOUT

Each line is `case endian hex`, endian 0 for big, 1 for little. Strings
are in omniORB's default native code set, ISO 8859-1 (as OpenRTM-aist
marshals them); the script also checks that omniORB refuses a string
with a character beyond Latin-1 rather than mangling it. omniORB leaves
alignment padding uninitialised (the test treats it as don't-care).
Within a value every number differs, so a member read in the wrong place
cannot go unseen; cdr_golden.rs builds the same values.
"""

import os
import shutil
import subprocess
import sys
import tempfile

IDL_FILES = ["BasicDataType.idl", "ExtendedDataTypes.idl", "InterfaceDataTypes.idl"]


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    checkout = sys.argv[1]
    idl_dir = os.path.join(checkout, "src", "lib", "rtm", "idl")
    commit = subprocess.run(
        ["git", "-C", checkout, "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip() or "unknown"
    out_dir = tempfile.mkdtemp()
    for name in IDL_FILES:
        shutil.copy(os.path.join(idl_dir, name), out_dir)
    subprocess.run(
        ["omniidl", "-bpython", "-C" + out_dir, "-I" + out_dir]
        + [os.path.join(out_dir, name) for name in IDL_FILES],
        check=True,
    )
    sys.path.insert(0, out_dir)
    import omniORB
    from omniORB import CORBA
    import RTC

    CORBA.ORB_init([], CORBA.ORB_ID)
    lines = [f"# n-ando/OpenRTM-aist {commit} InterfaceDataTypes.idl, omniORB {omniORB.__version__}"]
    for name, value in cases(RTC):
        tc = omniORB.tcInternal.typeCodeFromClassOrRepoId(type(value))
        for endian in (0, 1):
            lines.append(f"{name} {endian} {omniORB.cdrMarshal(tc, value, endian).hex()}")
    beyond = RTC.CameraImage(RTC.Time(1, 2), 1, 1, 8, "\u20ac", 1.0, b"\x00")
    try:
        omniORB.cdrMarshal(omniORB.tcInternal.typeCodeFromClassOrRepoId(RTC.CameraImage), beyond, 1)
        sys.exit("omniORB marshalled a string beyond Latin-1")
    except CORBA.DATA_CONVERSION:
        pass
    path = os.path.join(os.path.dirname(os.path.abspath(__file__)), "interface_vectors.txt")
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")
    print(f"{len(lines) - 1} vectors from {commit}")


def cases(RTC):
    tm = RTC.Time(0x01020304, 0x0A0B0C0D)
    geometry = lambda base: RTC.Geometry3D(
        RTC.Pose3D(RTC.Point3D(base + 0.1, base + 0.2, base + 0.3),
                   RTC.Orientation3D(base + 0.4, base + 0.5, base + 0.6)),
        RTC.Size3D(base + 0.7, base + 0.8, base + 0.9),
    )
    ranger_geometry = RTC.RangerGeometry(geometry(10), [geometry(20), geometry(30)])
    ranger_config = RTC.RangerConfig(-2.1, 2.2, 0.003, 0.04, 30.5, 0.006, 40.0)
    return [
        ("ActArrayActuatorPos", RTC.ActArrayActuatorPos(tm, 3, 1.25)),
        ("ActArrayActuatorSpeed", RTC.ActArrayActuatorSpeed(tm, 65535, -0.5)),
        ("ActArrayActuatorCurrent", RTC.ActArrayActuatorCurrent(tm, 0, 2.75)),
        ("CameraImage", RTC.CameraImage(tm, 3, 2, 24, "RGB", 1.5, bytes(range(18)))),
        ("CameraImage_latin1", RTC.CameraImage(tm, 1, 1, 8, "caf\u00e9 \u00c5\u00ff", 0.0, b"\xfe")),
        ("CameraImage_empty", RTC.CameraImage(tm, 0, 0, 0, "", 0.0, b"")),
        ("CameraInfo", RTC.CameraInfo(RTC.Vector2D(1.1, 1.2), RTC.Point2D(2.1, 2.2), 3.1, -3.2, 3.3, -3.4)),
        ("GPSTime", RTC.GPSTime(4000000000, 999)),
        ("GPSData", RTC.GPSData(tm, RTC.GPSTime(7, 8), 35.1, 139.2, 40.3, 1.4, 2.5, 0.6, 3.7, -0.8, 9, RTC.GPS_FIX_DGPS)),
        ("GPSData_no_fix", RTC.GPSData(tm, RTC.GPSTime(0, 0), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, RTC.GPS_FIX_NONE)),
        ("GripperState", RTC.GripperState(tm, RTC.GRIPPER_STATE_UNKNOWN)),
        ("INSData", RTC.INSData(tm, 35.1, 139.2, 40.3, 41.4,
                                RTC.Velocity3D(5.1, -5.2, 5.3, -5.4, 5.5, -5.6),
                                RTC.Orientation3D(6.1, -6.2, 6.3))),
        ("PointCloudPoint", RTC.PointCloudPoint(RTC.Point3D(1.1, 1.2, 1.3), RTC.RGBColour(0.1, 0.2, 0.3))),
        ("PointCloud", RTC.PointCloud(tm, [
            RTC.PointCloudPoint(RTC.Point3D(1.1, 1.2, 1.3), RTC.RGBColour(0.1, 0.2, 0.3)),
            RTC.PointCloudPoint(RTC.Point3D(-2.1, -2.2, -2.3), RTC.RGBColour(0.4, 0.5, 0.6)),
        ])),
        ("PointCloud_empty", RTC.PointCloud(tm, [])),
        ("PanTiltAngles", RTC.PanTiltAngles(tm, 0.1, -0.2)),
        ("PanTiltState", RTC.PanTiltState(tm, RTC.PanTiltAngles(RTC.Time(5, 6), 0.1, -0.2), 0.3, -0.4)),
        ("RangerGeometry", ranger_geometry),
        ("RangerConfig", ranger_config),
        ("RangeData", RTC.RangeData(tm, [0.5, 1.5, 2.5, 30.0], ranger_geometry, ranger_config)),
        ("RangeData_empty", RTC.RangeData(tm, [], RTC.RangerGeometry(geometry(0), []), ranger_config)),
        ("IntensityData", RTC.IntensityData(tm, [100.0, 200.5], ranger_geometry, ranger_config)),
    ]


if __name__ == "__main__":
    main()
