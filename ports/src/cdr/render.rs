//! [`render()`]: a CDR body shown as the `{:?}` of the value it holds,
//! picked by the name of its type (its `PortData::TYPE_NAME`, as a port's
//! announcement and its messages' `type` property carry it), for tools
//! that learn a port's type at run time (`leveretctl port echo`). It uses
//! only the CDR port data types of `cdr` and their `PortData` impls.

use super::*;
use crate::PortData;

/// The CDR port data types [`render()`] knows, one line each.
macro_rules! renderable {
    ($($t:ty),* $(,)?) => {
        /// The `{:?}` of the value `body` holds, for the CDR port data
        /// type named `type_name` (`IDL:RTC/TimedPose2D:1.0`…) in the byte
        /// order and charset of `options`; `None` for a type this crate
        /// does not implement, or a body that does not decode as it.
        pub fn render(type_name: &str, body: Bytes, options: CdrOptions) -> Option<String> {
            $(
                if <$t as PortData>::TYPE_NAME == Some(type_name) {
                    return <$t as PortData>::decode_with(body, options)
                        .ok()
                        .map(|value| format!("{value:?}"));
                }
            )*
            None
        }

        /// The types listed, by name.
        #[cfg(test)]
        const LISTED: &[&str] = &[$(stringify!($t)),*];

        #[cfg(test)]
        #[test]
        fn every_listed_type_renders_as_its_debug_form() {
            $(
                let value = <$t>::default();
                let mut body = BytesMut::new();
                value.encode(&mut body).expect("encode");
                let name = <$t as PortData>::TYPE_NAME.expect("a CDR type has a name");
                assert_eq!(
                    render(name, body.freeze(), CdrOptions::default()),
                    Some(format!("{value:?}")),
                    "{name}"
                );
            )*
        }
    };
}

renderable!(
    Time,
    TimedState,
    TimedShort,
    TimedLong,
    TimedUShort,
    TimedULong,
    TimedFloat,
    TimedDouble,
    TimedChar,
    TimedWChar,
    TimedBoolean,
    TimedOctet,
    TimedString,
    TimedWString,
    TimedShortSeq,
    TimedLongSeq,
    TimedUShortSeq,
    TimedULongSeq,
    TimedFloatSeq,
    TimedDoubleSeq,
    TimedCharSeq,
    TimedWCharSeq,
    TimedBooleanSeq,
    TimedOctetSeq,
    TimedStringSeq,
    TimedWStringSeq,
    RGBColour,
    Point2D,
    Vector2D,
    Pose2D,
    Velocity2D,
    Acceleration2D,
    PoseVel2D,
    Size2D,
    Geometry2D,
    Covariance2D,
    PointCovariance2D,
    Carlike,
    SpeedHeading2D,
    Point3D,
    Vector3D,
    Orientation3D,
    Pose3D,
    Velocity3D,
    AngularVelocity3D,
    Acceleration3D,
    AngularAcceleration3D,
    PoseVel3D,
    Size3D,
    Geometry3D,
    Covariance3D,
    SpeedHeading3D,
    OAP,
    Quaternion,
    TimedRGBColour,
    TimedPoint2D,
    TimedVector2D,
    TimedPose2D,
    TimedVelocity2D,
    TimedAcceleration2D,
    TimedPoseVel2D,
    TimedSize2D,
    TimedGeometry2D,
    TimedCovariance2D,
    TimedPointCovariance2D,
    TimedCarlike,
    TimedSpeedHeading2D,
    TimedPoint3D,
    TimedVector3D,
    TimedOrientation3D,
    TimedPose3D,
    TimedVelocity3D,
    TimedAngularVelocity3D,
    TimedAcceleration3D,
    TimedAngularAcceleration3D,
    TimedPoseVel3D,
    TimedSize3D,
    TimedGeometry3D,
    TimedCovariance3D,
    TimedSpeedHeading3D,
    TimedOAP,
    TimedQuaternion,
    ActArrayActuatorPos,
    ActArrayActuatorSpeed,
    ActArrayActuatorCurrent,
    CameraImage,
    CameraInfo,
    GPSTime,
    GPSData,
    GripperState,
    INSData,
    PointCloudPoint,
    PointCloud,
    PanTiltAngles,
    PanTiltState,
    RangerGeometry,
    RangerConfig,
    RangeData,
    IntensityData,
);

#[cfg(test)]
mod tests {
    use super::*;

    /// The types `idl_structs!` and `timed_structs!` declare in a source
    /// file: a four-space-indented name opening a struct body (`Name {`,
    /// `Name [Copy] {`) or a timed wrapper (`TimedName(…)`).
    fn declared(source: &str) -> Vec<&str> {
        source
            .lines()
            .filter_map(|line| line.strip_prefix("    "))
            .filter(|line| line.starts_with(|c: char| c.is_ascii_uppercase()))
            .filter(|line| line.trim_end().ends_with('{') || line.starts_with("Timed"))
            .filter_map(|line| line.split(|c: char| !c.is_ascii_alphanumeric()).next())
            .collect()
    }

    #[test]
    fn every_declared_type_is_listed() {
        let declared: Vec<&str> = [
            include_str!("basic.rs"),
            include_str!("extended.rs"),
            include_str!("interface.rs"),
        ]
        .into_iter()
        .flat_map(declared)
        .collect();
        assert!(declared.len() > 70, "found {}", declared.len());
        for name in declared {
            assert!(LISTED.contains(&name), "{name} is not renderable");
        }
    }

    #[test]
    fn values_render_in_their_byte_order_and_unknown_types_not_at_all() {
        let pose = TimedPose2D {
            tm: Time { sec: 1, nsec: 2 },
            data: Pose2D {
                position: Point2D { x: 1.5, y: -2.0 },
                heading: 0.25,
            },
        };
        let big = CdrOptions {
            endian: Endian::Big,
            ..CdrOptions::default()
        };
        let mut body = BytesMut::new();
        encode_with(&pose, &mut body, big).expect("encode");
        let body = body.freeze();
        let name = "IDL:RTC/TimedPose2D:1.0";
        assert_eq!(render(name, body.clone(), big), Some(format!("{pose:?}")));
        assert!(format!("{pose:?}").contains("heading: 0.25"));
        // Read in the wrong byte order it is not a pose (or not this one).
        assert_ne!(
            render(name, body.clone(), CdrOptions::default()),
            Some(format!("{pose:?}"))
        );
        assert_eq!(render("IDL:RTC/TimedPose3D:1.0", body.clone(), big), None);
        assert_eq!(render("", body.clone(), big), None);
        assert_eq!(render(name, body.slice(..10), big), None);
    }
}
