//! CDR byte for byte against omniORB: `golden/cdr_vectors.txt` holds
//! values marshalled by omniORB's `cdrMarshal` in both byte orders
//! (written by `golden/generate_cdr_vectors.py`, and
//! `golden/interface_vectors.txt` by `golden/generate_interface_vectors.py`
//! from OpenRTM-aist's InterfaceDataTypes.idl); each must decode to the
//! value it was made from, and encoding that value must give the same
//! bytes, padding aside (omniORB leaves alignment padding uninitialised:
//! there a golden byte may differ from the zero this crate writes).

use bytes::{Bytes, BytesMut};
use leveret_ports::{
    CdrOptions, Charset, Endian, Point2D, PortData, Pose2D, Time, TimedBoolean, TimedBooleanSeq,
    TimedChar, TimedCharSeq, TimedDouble, TimedDoubleSeq, TimedFloat, TimedFloatSeq, TimedLong,
    TimedLongSeq, TimedOctet, TimedOctetSeq, TimedPose2D, TimedShort, TimedShortSeq, TimedState,
    TimedString, TimedStringSeq, TimedULong, TimedULongSeq, TimedUShort, TimedUShortSeq,
    TimedVelocity2D, TimedWChar, TimedWCharSeq, TimedWString, TimedWStringSeq, Velocity2D, WString,
};
use std::fmt::Debug;

const VECTORS: &str = include_str!("golden/cdr_vectors.txt");
/// InterfaceDataTypes.idl's, from OpenRTM-aist's own IDL (written by
/// `golden/generate_interface_vectors.py`).
const INTERFACE_VECTORS: &str = include_str!("golden/interface_vectors.txt");

const TM: Time = Time {
    sec: 0x0102_0304,
    nsec: 0x0a0b_0c0d,
};

fn golden(case: &str, endian: Endian) -> Vec<u8> {
    let order = match endian {
        Endian::Big => "0",
        Endian::Little => "1",
    };
    let line = VECTORS
        .lines()
        .chain(INTERFACE_VECTORS.lines())
        .find(|line| {
            let mut fields = line.split(' ');
            fields.next() == Some(case) && fields.next() == Some(order)
        })
        .unwrap_or_else(|| panic!("no vector for {case} {order}"));
    let hex = line.rsplit(' ').next().unwrap();
    (0..hex.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
        .collect()
}

fn check<T: PortData + PartialEq + Debug>(case: &str, value: T, charset: Charset) {
    for endian in [Endian::Big, Endian::Little] {
        let options = CdrOptions { endian, charset };
        let expected = golden(case, endian);
        let decoded = T::decode_with(Bytes::from(expected.clone()), options)
            .unwrap_or_else(|e| panic!("{case} {endian:?}: {e}"));
        assert_eq!(decoded, value, "{case} {endian:?} decodes");
        let mut ours = BytesMut::new();
        value.encode_with(&mut ours, options).unwrap();
        assert_eq!(ours.len(), expected.len(), "{case} {endian:?} length");
        for (i, (a, b)) in ours.iter().zip(&expected).enumerate() {
            // A difference may only be padding: a zero of ours that the
            // decode above skipped (a data byte there would have changed
            // the decoded value).
            assert!(
                a == b || *a == 0,
                "{case} {endian:?} byte {i}: ours {a:#04x}, omniORB {b:#04x}"
            );
        }
    }
}

#[test]
fn timed_scalars() {
    check(
        "timed_double",
        TimedDouble { tm: TM, data: 3.25 },
        Charset::Utf8,
    );
    check(
        "timed_double_negative",
        TimedDouble {
            tm: Time { sec: 1, nsec: 2 },
            data: -1.0e-300,
        },
        Charset::Utf8,
    );
    check("timed_long", TimedLong { tm: TM, data: -2 }, Charset::Utf8);
}

#[test]
fn timed_strings() {
    let text = |data: &str| TimedString {
        tm: TM,
        data: data.into(),
    };
    check("timed_string", text("go"), Charset::Utf8);
    check("timed_string_empty", text(""), Charset::Utf8);
    check("timed_string_latin1", text("café Å"), Charset::Latin1);
}

#[test]
fn timed_sequences() {
    let seq = |data: Vec<f64>| TimedDoubleSeq { tm: TM, data };
    check(
        "timed_double_seq",
        seq(vec![1.5, -2.0, 1.0e300]),
        Charset::Utf8,
    );
    check("timed_double_seq_empty", seq(vec![]), Charset::Utf8);
}

#[test]
fn timed_2d_geometry() {
    check(
        "timed_pose2d",
        TimedPose2D {
            tm: TM,
            data: Pose2D {
                position: Point2D { x: 1.0, y: 2.0 },
                heading: 0.5,
            },
        },
        Charset::Utf8,
    );
    check(
        "timed_velocity2d",
        TimedVelocity2D {
            tm: TM,
            data: Velocity2D {
                vx: 0.1,
                vy: 0.2,
                va: 0.3,
            },
        },
        Charset::Utf8,
    );
}

#[test]
fn basic_timed_scalars() {
    check(
        "timed_state",
        TimedState { tm: TM, data: -3 },
        Charset::Utf8,
    );
    check(
        "timed_short",
        TimedShort { tm: TM, data: -300 },
        Charset::Utf8,
    );
    check(
        "timed_ushort",
        TimedUShort {
            tm: TM,
            data: 65000,
        },
        Charset::Utf8,
    );
    check(
        "timed_ulong",
        TimedULong {
            tm: TM,
            data: 4_000_000_000,
        },
        Charset::Utf8,
    );
    check(
        "timed_float",
        TimedFloat { tm: TM, data: 1.5 },
        Charset::Utf8,
    );
    check(
        "timed_char",
        TimedChar { tm: TM, data: b'A' },
        Charset::Utf8,
    );
    check(
        "timed_boolean",
        TimedBoolean { tm: TM, data: true },
        Charset::Utf8,
    );
    check(
        "timed_octet",
        TimedOctet { tm: TM, data: 0xfe },
        Charset::Utf8,
    );
}

#[test]
fn basic_timed_sequences() {
    check(
        "timed_short_seq",
        TimedShortSeq {
            tm: TM,
            data: vec![1, -2, 3],
        },
        Charset::Utf8,
    );
    check(
        "timed_long_seq",
        TimedLongSeq {
            tm: TM,
            data: vec![7, -8],
        },
        Charset::Utf8,
    );
    check(
        "timed_ushort_seq",
        TimedUShortSeq {
            tm: TM,
            data: vec![1, 65535],
        },
        Charset::Utf8,
    );
    check(
        "timed_ulong_seq",
        TimedULongSeq {
            tm: TM,
            data: vec![1, u32::MAX],
        },
        Charset::Utf8,
    );
    check(
        "timed_float_seq",
        TimedFloatSeq {
            tm: TM,
            data: vec![0.5, -0.25],
        },
        Charset::Utf8,
    );
    check(
        "timed_char_seq",
        TimedCharSeq {
            tm: TM,
            data: b"hi".to_vec(),
        },
        Charset::Utf8,
    );
    check(
        "timed_boolean_seq",
        TimedBooleanSeq {
            tm: TM,
            data: vec![true, false, true],
        },
        Charset::Utf8,
    );
    check(
        "timed_octet_seq",
        TimedOctetSeq {
            tm: TM,
            data: vec![0, 1, 0xff],
        },
        Charset::Utf8,
    );
    check(
        "timed_string_seq",
        TimedStringSeq {
            tm: TM,
            data: vec!["a".into(), String::new(), "bcd".into()],
        },
        Charset::Utf8,
    );
}

/// The wide-character types: UTF-16, the same bytes in either charset
/// (the charset is for `string`s); omniORB writes a `wstring`'s units
/// little-endian after the mark `FF FE` in both byte orders, a `wchar`
/// big-endian without a mark. The C++ way OpenRTM-aist marshals them gave
/// the same bytes (`golden/openrtm_cxx_wide.cc`).
#[test]
fn basic_wide_characters() {
    for charset in [Charset::Utf8, Charset::Latin1] {
        let wchar = |data: char| TimedWChar { tm: TM, data };
        check("timed_wchar", wchar('\u{3a9}'), charset);
        check("timed_wchar_ascii", wchar('A'), charset);
        let wstring = |data: &str| TimedWString {
            tm: TM,
            data: data.into(),
        };
        check("timed_wstring", wstring("A\u{e9}\u{20ac}"), charset);
        check("timed_wstring_empty", wstring(""), charset);
        check("timed_wstring_surrogates", wstring("x\u{1f600}"), charset);
        // U+FEFF as the first character, after the mark.
        check("timed_wstring_feff", wstring("\u{feff}A"), charset);
        let chars = |data: Vec<char>| TimedWCharSeq { tm: TM, data };
        check(
            "timed_wchar_seq",
            chars(vec!['a', '\u{3a9}', '\u{20ac}']),
            charset,
        );
        check("timed_wchar_seq_empty", chars(vec![]), charset);
        check(
            "timed_wstring_seq",
            TimedWStringSeq {
                tm: TM,
                data: ["a", "", "\u{3a9}\u{3bc}", "x\u{1f600}"]
                    .map(WString::from)
                    .to_vec(),
            },
            charset,
        );
    }
}

/// Every type of `ExtendedDataTypes.idl`, bare and time-stamped, as
/// `generate_cdr_vectors.py`'s `extended_cases` built them: within a value
/// every double differs.
mod extended {
    use super::{check, TM};
    use leveret_ports::{
        Acceleration2D, Acceleration3D, AngularAcceleration3D, AngularVelocity3D, Carlike, Charset,
        Covariance2D, Covariance3D, Geometry2D, Geometry3D, Orientation3D, Point2D, Point3D,
        PointCovariance2D, PortData, Pose2D, Pose3D, PoseVel2D, PoseVel3D, Quaternion, RGBColour,
        Size2D, Size3D, SpeedHeading2D, SpeedHeading3D, TimedAcceleration2D, TimedAcceleration3D,
        TimedAngularAcceleration3D, TimedAngularVelocity3D, TimedCarlike, TimedCovariance2D,
        TimedCovariance3D, TimedGeometry2D, TimedGeometry3D, TimedOAP, TimedOrientation3D,
        TimedPoint2D, TimedPoint3D, TimedPointCovariance2D, TimedPose2D, TimedPose3D,
        TimedPoseVel2D, TimedPoseVel3D, TimedQuaternion, TimedRGBColour, TimedSize2D, TimedSize3D,
        TimedSpeedHeading2D, TimedSpeedHeading3D, TimedVector2D, TimedVector3D, TimedVelocity2D,
        TimedVelocity3D, Vector2D, Vector3D, Velocity2D, Velocity3D, OAP,
    };
    use std::fmt::Debug;

    /// The case named as the type, and the one named as its `Timed*` form
    /// (the same value stamped with `TM`).
    fn both<T, U>(value: T, timed: impl FnOnce(T) -> U)
    where
        T: PortData + PartialEq + Debug + Clone,
        U: PortData + PartialEq + Debug,
    {
        let name = |t: &str| t.rsplit(['/', ':']).nth(1).unwrap().to_owned();
        let bare = name(T::TYPE_NAME.unwrap());
        let stamped = name(U::TYPE_NAME.unwrap());
        assert_eq!(stamped, format!("Timed{bare}"));
        check(&bare, value.clone(), Charset::Utf8);
        check(&stamped, timed(value), Charset::Utf8);
    }

    fn point2d() -> Point2D {
        Point2D { x: 1.1, y: -1.2 }
    }

    fn pose2d() -> Pose2D {
        Pose2D {
            position: point2d(),
            heading: 1.3,
        }
    }

    fn velocity2d() -> Velocity2D {
        Velocity2D {
            vx: 3.1,
            vy: -3.2,
            va: 3.3,
        }
    }

    fn size2d() -> Size2D {
        Size2D { l: 5.1, w: 5.2 }
    }

    fn point3d() -> Point3D {
        Point3D {
            x: 11.1,
            y: -11.2,
            z: 11.3,
        }
    }

    fn vector3d() -> Vector3D {
        Vector3D {
            x: 12.1,
            y: -12.2,
            z: 12.3,
        }
    }

    fn orientation3d() -> Orientation3D {
        Orientation3D {
            r: 13.1,
            p: -13.2,
            y: 13.3,
        }
    }

    fn pose3d() -> Pose3D {
        Pose3D {
            position: point3d(),
            orientation: orientation3d(),
        }
    }

    fn velocity3d() -> Velocity3D {
        Velocity3D {
            vx: 14.1,
            vy: -14.2,
            vz: 14.3,
            vr: -14.4,
            vp: 14.5,
            va: -14.6,
        }
    }

    fn size3d() -> Size3D {
        Size3D {
            l: 18.1,
            w: 18.2,
            h: 18.3,
        }
    }

    #[test]
    fn colour_and_2d() {
        both(
            RGBColour {
                r: 0.1,
                g: 0.6,
                b: 0.9,
            },
            |data| TimedRGBColour { tm: TM, data },
        );
        both(point2d(), |data| TimedPoint2D { tm: TM, data });
        both(Vector2D { x: 2.1, y: -2.2 }, |data| TimedVector2D {
            tm: TM,
            data,
        });
        both(pose2d(), |data| TimedPose2D { tm: TM, data });
        both(velocity2d(), |data| TimedVelocity2D { tm: TM, data });
        both(Acceleration2D { ax: 4.1, ay: -4.2 }, |data| {
            TimedAcceleration2D { tm: TM, data }
        });
        both(
            PoseVel2D {
                pose: pose2d(),
                velocities: velocity2d(),
            },
            |data| TimedPoseVel2D { tm: TM, data },
        );
        both(size2d(), |data| TimedSize2D { tm: TM, data });
        both(
            Geometry2D {
                pose: pose2d(),
                size: size2d(),
            },
            |data| TimedGeometry2D { tm: TM, data },
        );
        both(
            Covariance2D {
                xx: 6.1,
                xy: -6.2,
                xt: 6.3,
                yy: -6.4,
                yt: 6.5,
                tt: -6.6,
            },
            |data| TimedCovariance2D { tm: TM, data },
        );
        both(
            PointCovariance2D {
                xx: 7.1,
                xy: -7.2,
                yy: 7.3,
            },
            |data| TimedPointCovariance2D { tm: TM, data },
        );
        both(
            Carlike {
                speed: 8.1,
                steering_angle: -8.2,
            },
            |data| TimedCarlike { tm: TM, data },
        );
        both(
            SpeedHeading2D {
                speed: 9.1,
                heading: -9.2,
            },
            |data| TimedSpeedHeading2D { tm: TM, data },
        );
    }

    #[test]
    fn three_d() {
        both(point3d(), |data| TimedPoint3D { tm: TM, data });
        both(vector3d(), |data| TimedVector3D { tm: TM, data });
        both(orientation3d(), |data| TimedOrientation3D { tm: TM, data });
        both(pose3d(), |data| TimedPose3D { tm: TM, data });
        both(velocity3d(), |data| TimedVelocity3D { tm: TM, data });
        both(
            AngularVelocity3D {
                avx: 15.1,
                avy: -15.2,
                avz: 15.3,
            },
            |data| TimedAngularVelocity3D { tm: TM, data },
        );
        both(
            Acceleration3D {
                ax: 16.1,
                ay: -16.2,
                az: 16.3,
            },
            |data| TimedAcceleration3D { tm: TM, data },
        );
        both(
            AngularAcceleration3D {
                aax: 17.1,
                aay: -17.2,
                aaz: 17.3,
            },
            |data| TimedAngularAcceleration3D { tm: TM, data },
        );
        both(
            PoseVel3D {
                pose: pose3d(),
                velocities: velocity3d(),
            },
            |data| TimedPoseVel3D { tm: TM, data },
        );
        both(size3d(), |data| TimedSize3D { tm: TM, data });
        both(
            Geometry3D {
                pose: pose3d(),
                size: size3d(),
            },
            |data| TimedGeometry3D { tm: TM, data },
        );
        both(
            Covariance3D {
                xx: 19.01,
                xy: -19.02,
                xz: 19.03,
                xr: -19.04,
                xp: 19.05,
                xa: -19.06,
                yy: 19.07,
                yz: -19.08,
                yr: 19.09,
                yp: -19.10,
                ya: 19.11,
                zz: -19.12,
                zr: 19.13,
                zp: -19.14,
                za: 19.15,
                rr: -19.16,
                rp: 19.17,
                ra: -19.18,
                pp: 19.19,
                pa: -19.20,
                aa: 19.21,
            },
            |data| TimedCovariance3D { tm: TM, data },
        );
        both(
            SpeedHeading3D {
                speed: 20.1,
                direction: orientation3d(),
            },
            |data| TimedSpeedHeading3D { tm: TM, data },
        );
        both(
            OAP {
                orientation: vector3d(),
                approach: Vector3D {
                    x: 21.1,
                    y: -21.2,
                    z: 21.3,
                },
                position: Vector3D {
                    x: 22.1,
                    y: -22.2,
                    z: 22.3,
                },
            },
            |data| TimedOAP { tm: TM, data },
        );
        both(
            Quaternion {
                x: 23.1,
                y: -23.2,
                z: 23.3,
                w: -23.4,
            },
            |data| TimedQuaternion { tm: TM, data },
        );
    }

    #[test]
    fn the_vectors_hold_the_56_types_in_both_byte_orders() {
        // Their cases are named as the types (capitalised), the basic
        // ones in snake case.
        let extended = super::VECTORS
            .lines()
            .filter(|line| line.starts_with(|c: char| c.is_ascii_uppercase()))
            .count();
        assert_eq!(extended, 56 * 2);
    }
}

/// InterfaceDataTypes.idl: the values `generate_interface_vectors.py`
/// marshalled, built here.
mod interface {
    use super::{check, TM};
    use leveret_ports::*;

    fn geometry(base: f64) -> Geometry3D {
        Geometry3D {
            pose: Pose3D {
                position: Point3D {
                    x: base + 0.1,
                    y: base + 0.2,
                    z: base + 0.3,
                },
                orientation: Orientation3D {
                    r: base + 0.4,
                    p: base + 0.5,
                    y: base + 0.6,
                },
            },
            size: Size3D {
                l: base + 0.7,
                w: base + 0.8,
                h: base + 0.9,
            },
        }
    }

    fn ranger_geometry() -> RangerGeometry {
        RangerGeometry {
            geometry: geometry(10.0),
            element_geometries: vec![geometry(20.0), geometry(30.0)],
        }
    }

    const RANGER_CONFIG: RangerConfig = RangerConfig {
        min_angle: -2.1,
        max_angle: 2.2,
        angular_res: 0.003,
        min_range: 0.04,
        max_range: 30.5,
        range_res: 0.006,
        frequency: 40.0,
    };

    const POINTS: [PointCloudPoint; 2] = [
        PointCloudPoint {
            point: Point3D {
                x: 1.1,
                y: 1.2,
                z: 1.3,
            },
            colour: RGBColour {
                r: 0.1,
                g: 0.2,
                b: 0.3,
            },
        },
        PointCloudPoint {
            point: Point3D {
                x: -2.1,
                y: -2.2,
                z: -2.3,
            },
            colour: RGBColour {
                r: 0.4,
                g: 0.5,
                b: 0.6,
            },
        },
    ];

    #[test]
    fn actuators_grippers_and_pan_tilt_units() {
        let latin1 = Charset::Latin1;
        check(
            "ActArrayActuatorPos",
            ActArrayActuatorPos {
                tm: TM,
                index: 3,
                position: 1.25,
            },
            latin1,
        );
        check(
            "ActArrayActuatorSpeed",
            ActArrayActuatorSpeed {
                tm: TM,
                index: 65535,
                speed: -0.5,
            },
            latin1,
        );
        check(
            "ActArrayActuatorCurrent",
            ActArrayActuatorCurrent {
                tm: TM,
                index: 0,
                current: 2.75,
            },
            latin1,
        );
        check(
            "GripperState",
            GripperState {
                tm: TM,
                status: GripperStatus::Unknown,
            },
            latin1,
        );
        let angles = PanTiltAngles {
            tm: TM,
            pan: 0.1,
            tilt: -0.2,
        };
        check("PanTiltAngles", angles, latin1);
        check(
            "PanTiltState",
            PanTiltState {
                tm: TM,
                angles: PanTiltAngles {
                    tm: Time { sec: 5, nsec: 6 },
                    ..angles
                },
                pan_speed: 0.3,
                tilt_speed: -0.4,
            },
            latin1,
        );
    }

    #[test]
    fn cameras_with_latin1_format_strings() {
        let latin1 = Charset::Latin1;
        check(
            "CameraImage",
            CameraImage {
                tm: TM,
                width: 3,
                height: 2,
                bpp: 24,
                format: "RGB".into(),
                f_div: 1.5,
                pixels: (0..18).collect(),
            },
            latin1,
        );
        check(
            "CameraImage_latin1",
            CameraImage {
                tm: TM,
                width: 1,
                height: 1,
                bpp: 8,
                format: "café Åÿ".into(),
                f_div: 0.0,
                pixels: vec![0xfe],
            },
            latin1,
        );
        check(
            "CameraImage_empty",
            CameraImage {
                tm: TM,
                ..CameraImage::default()
            },
            latin1,
        );
        check(
            "CameraInfo",
            CameraInfo {
                focal_length: Vector2D { x: 1.1, y: 1.2 },
                principal_point: Point2D { x: 2.1, y: 2.2 },
                k1: 3.1,
                k2: -3.2,
                p1: 3.3,
                p2: -3.4,
            },
            latin1,
        );
    }

    #[test]
    fn gps_and_inertial_navigation() {
        let latin1 = Charset::Latin1;
        check(
            "GPSTime",
            GPSTime {
                sec: 4_000_000_000,
                msec: 999,
            },
            latin1,
        );
        check(
            "GPSData",
            GPSData {
                tm: TM,
                time_from_gps: GPSTime { sec: 7, msec: 8 },
                latitude: 35.1,
                longitude: 139.2,
                altitude: 40.3,
                horizontal_error: 1.4,
                vertical_error: 2.5,
                heading: 0.6,
                horizontal_speed: 3.7,
                vertical_speed: -0.8,
                num_satellites: 9,
                fix_type: GPSFixType::Dgps,
            },
            latin1,
        );
        check(
            "GPSData_no_fix",
            GPSData {
                tm: TM,
                ..GPSData::default()
            },
            latin1,
        );
        check(
            "INSData",
            INSData {
                tm: TM,
                latitude: 35.1,
                longitude: 139.2,
                altitude: 40.3,
                height_amsl: 41.4,
                velocity_enu: Velocity3D {
                    vx: 5.1,
                    vy: -5.2,
                    vz: 5.3,
                    vr: -5.4,
                    vp: 5.5,
                    va: -5.6,
                },
                orientation: Orientation3D {
                    r: 6.1,
                    p: -6.2,
                    y: 6.3,
                },
            },
            latin1,
        );
    }

    #[test]
    fn point_clouds_and_range_scans() {
        let latin1 = Charset::Latin1;
        check("PointCloudPoint", POINTS[0], latin1);
        check(
            "PointCloud",
            PointCloud {
                tm: TM,
                points: POINTS.to_vec(),
            },
            latin1,
        );
        check(
            "PointCloud_empty",
            PointCloud {
                tm: TM,
                points: vec![],
            },
            latin1,
        );
        check("RangerGeometry", ranger_geometry(), latin1);
        check("RangerConfig", RANGER_CONFIG, latin1);
        check(
            "RangeData",
            RangeData {
                tm: TM,
                ranges: vec![0.5, 1.5, 2.5, 30.0],
                geometry: ranger_geometry(),
                config: RANGER_CONFIG,
            },
            latin1,
        );
        check(
            "RangeData_empty",
            RangeData {
                tm: TM,
                ranges: vec![],
                geometry: RangerGeometry {
                    geometry: geometry(0.0),
                    element_geometries: vec![],
                },
                config: RANGER_CONFIG,
            },
            latin1,
        );
        check(
            "IntensityData",
            IntensityData {
                tm: TM,
                intensities: vec![100.0, 200.5],
                geometry: ranger_geometry(),
                config: RANGER_CONFIG,
            },
            latin1,
        );
    }

    /// What OpenRTM-aist sends is ISO 8859-1: read as UTF-8 its "é" is
    /// not text, and a character beyond Latin-1 is refused when encoding
    /// (as omniORB refuses it: the script checks), not mangled.
    #[test]
    fn latin1_is_what_omniorb_sends_and_beyond_it_is_refused() {
        let body = bytes::Bytes::from(super::golden("CameraImage_latin1", Endian::Little));
        let utf8 = CdrOptions {
            endian: Endian::Little,
            charset: Charset::Utf8,
        };
        assert!(CameraImage::decode_with(body, utf8).is_err());
        let euro = CameraImage {
            format: "€".into(),
            ..CameraImage::default()
        };
        let latin1 = CdrOptions {
            endian: Endian::Little,
            charset: Charset::Latin1,
        };
        let refused = euro
            .encode_with(&mut bytes::BytesMut::new(), latin1)
            .unwrap_err();
        assert!(refused.to_string().contains("Latin-1"), "{refused}");
    }

    #[test]
    fn the_vectors_hold_every_case_in_both_byte_orders() {
        let cases: Vec<&str> = super::INTERFACE_VECTORS
            .lines()
            .filter(|line| !line.starts_with('#'))
            .filter_map(|line| line.split(' ').next())
            .collect();
        assert_eq!(cases.len(), 22 * 2);
        assert!(super::INTERFACE_VECTORS.starts_with("# n-ando/OpenRTM-aist "));
    }
}
