//! Types of OpenRTM-aist's `InterfaceDataTypes.idl` (module `RTC`), the
//! data of its device interfaces: range finders ([`RangeData`],
//! [`IntensityData`]), cameras ([`CameraImage`], [`CameraInfo`]), point
//! clouds ([`PointCloud`]), GPS and inertial navigation ([`GPSData`],
//! [`INSData`]), pan-tilt units, grippers and single actuators. Members in
//! IDL order; IDL names in `camelCase` are `snake_case` here. An IDL
//! `enum` is an `unsigned long` in CDR; a value beyond its last member
//! does not decode. Not yet here: the map, feature, fiducial, hypothesis,
//! path, limb, bumper, multi-camera and actuator-array types.

use super::{Cdr, CdrElement, CdrReader, CdrWriter, Geometry3D, Orientation3D, Point2D, Point3D};
use super::{RGBColour, Time, Vector2D, Velocity3D};
use crate::DataError;

/// Declares IDL enums: each a Rust enum (its first member the default)
/// whose CDR form is the member's index as an `unsigned long`.
macro_rules! idl_enums {
    ($(
        $(#[$doc:meta])*
        enum $name:ident = [$($(#[$member_doc:meta])* $member:ident),+ $(,)?];
    )*) => {$(
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
        pub enum $name {
            #[default]
            $($(#[$member_doc])* $member,)+
        }

        impl $name {
            const MEMBERS: &'static [$name] = &[$($name::$member),+];
        }

        impl Cdr for $name {
            fn write_cdr(&self, out: &mut CdrWriter<'_>) -> Result<(), DataError> {
                out.ulong(*self as u32);
                Ok(())
            }

            fn read_cdr(input: &mut CdrReader) -> Result<Self, DataError> {
                let index = input.ulong()?;
                usize::try_from(index)
                    .ok()
                    .and_then(|i| $name::MEMBERS.get(i).copied())
                    .ok_or_else(|| {
                        DataError::Invalid(format!(
                            "{index} is not an RTC::{} (0..{})",
                            stringify!($name),
                            $name::MEMBERS.len()
                        ))
                    })
            }
        }
    )*};
}

idl_enums!(
    /// `RTC::GPSFixType`.
    enum GPSFixType = [
        /// `GPS_FIX_NONE`: no fix.
        None,
        /// `GPS_FIX_NORMAL`.
        Normal,
        /// `GPS_FIX_DGPS`: differential GPS.
        Dgps,
    ];

    /// `RTC::GripperStatus`.
    enum GripperStatus = [
        /// `GRIPPER_STATE_OPEN`.
        Open,
        /// `GRIPPER_STATE_CLOSED`.
        Closed,
        /// `GRIPPER_STATE_MOVING`.
        Moving,
        /// `GRIPPER_STATE_UNKNOWN`.
        Unknown,
    ];
);

idl_structs!(
    /// `RTC::ActArrayActuatorPos`: a position command for one actuator of
    /// an array.
    ActArrayActuatorPos [Copy] {
        /// Time stamp.
        tm: Time,
        /// The actuator's index in the array.
        index: u16,
        /// Target position, m or rad.
        position: f64,
    }

    /// `RTC::ActArrayActuatorSpeed`: a speed command for one actuator.
    ActArrayActuatorSpeed [Copy] {
        /// Time stamp.
        tm: Time,
        /// The actuator's index in the array.
        index: u16,
        /// Target speed, m/s or rad/s.
        speed: f64,
    }

    /// `RTC::ActArrayActuatorCurrent`: a current command for one actuator.
    ActArrayActuatorCurrent [Copy] {
        /// Time stamp.
        tm: Time,
        /// The actuator's index in the array.
        index: u16,
        /// Target current, A.
        current: f64,
    }

    /// `RTC::CameraImage`: one frame.
    CameraImage {
        /// Time stamp.
        tm: Time,
        /// Width, pixels.
        width: u16,
        /// Height, pixels.
        height: u16,
        /// Bits per pixel.
        bpp: u16,
        /// Image format (e.g. `RGB`, `JPEG`; a `string`: see `Charset`).
        format: String,
        /// Scale to divide pixel values by to get metres (depth images;
        /// IDL `fDiv`).
        f_div: f64,
        /// The pixels.
        pixels: Vec<u8>,
    }

    /// `RTC::CameraInfo`: intrinsics and distortion.
    CameraInfo [Copy] {
        /// Focal length, pixels (IDL `focalLength`).
        focal_length: Vector2D,
        /// Principal point, pixels (IDL `principalPoint`).
        principal_point: Point2D,
        /// First radial distortion coefficient.
        k1: f64,
        /// Second radial distortion coefficient.
        k2: f64,
        /// First tangential distortion coefficient.
        p1: f64,
        /// Second tangential distortion coefficient.
        p2: f64,
    }

    /// `RTC::GPSTime`: time as the GPS receiver gives it.
    GPSTime [Copy, Eq] {
        /// Seconds.
        sec: u32,
        /// Milliseconds.
        msec: u32,
    }

    /// `RTC::GPSData`: a GPS receiver's fix.
    GPSData [Copy] {
        /// Time stamp.
        tm: Time,
        /// Time from the receiver (IDL `timeFromGPS`).
        time_from_gps: GPSTime,
        /// Latitude, degrees.
        latitude: f64,
        /// Longitude, degrees.
        longitude: f64,
        /// Altitude, m.
        altitude: f64,
        /// Horizontal error, m (IDL `horizontalError`).
        horizontal_error: f64,
        /// Vertical error, m (IDL `verticalError`).
        vertical_error: f64,
        /// Heading, rad.
        heading: f64,
        /// Horizontal speed, m/s (IDL `horizontalSpeed`).
        horizontal_speed: f64,
        /// Vertical speed, m/s (IDL `verticalSpeed`).
        vertical_speed: f64,
        /// Satellites in view (IDL `numSatellites`).
        num_satellites: u16,
        /// Kind of fix (IDL `fixType`).
        fix_type: GPSFixType,
    }

    /// `RTC::GripperState`.
    GripperState [Copy] {
        /// Time stamp.
        tm: Time,
        /// The gripper's state.
        status: GripperStatus,
    }

    /// `RTC::INSData`: an inertial navigation system's estimate.
    INSData [Copy] {
        /// Time stamp.
        tm: Time,
        /// Latitude, degrees.
        latitude: f64,
        /// Longitude, degrees.
        longitude: f64,
        /// Altitude, m.
        altitude: f64,
        /// Height above mean sea level, m (IDL `heightAMSL`).
        height_amsl: f64,
        /// Velocity in east-north-up axes (IDL `velocityENU`).
        velocity_enu: Velocity3D,
        /// Orientation.
        orientation: Orientation3D,
    }

    /// `RTC::PointCloudPoint`: a point and its colour.
    PointCloudPoint [Copy] {
        /// Position.
        point: Point3D,
        /// Colour.
        colour: RGBColour,
    }

    /// `RTC::PointCloud`.
    PointCloud {
        /// Time stamp.
        tm: Time,
        /// The points.
        points: Vec<PointCloudPoint>,
    }

    /// `RTC::PanTiltAngles`.
    PanTiltAngles [Copy] {
        /// Time stamp.
        tm: Time,
        /// Pan, rad.
        pan: f64,
        /// Tilt, rad.
        tilt: f64,
    }

    /// `RTC::PanTiltState`.
    PanTiltState [Copy] {
        /// Time stamp.
        tm: Time,
        /// Current angles.
        angles: PanTiltAngles,
        /// Pan speed, rad/s (IDL `panSpeed`).
        pan_speed: f64,
        /// Tilt speed, rad/s (IDL `tiltSpeed`).
        tilt_speed: f64,
    }

    /// `RTC::RangerGeometry`: where a range sensor and each of its
    /// elements are.
    RangerGeometry {
        /// The sensor's geometry.
        geometry: Geometry3D,
        /// Each element's (IDL `elementGeometries`).
        element_geometries: Vec<Geometry3D>,
    }

    /// `RTC::RangerConfig`: a range sensor's scan.
    RangerConfig [Copy] {
        /// First angle scanned, rad (IDL `minAngle`).
        min_angle: f64,
        /// Last angle scanned, rad (IDL `maxAngle`).
        max_angle: f64,
        /// Angle between readings, rad (IDL `angularRes`).
        angular_res: f64,
        /// Shortest range, m (IDL `minRange`).
        min_range: f64,
        /// Longest range, m (IDL `maxRange`).
        max_range: f64,
        /// Range resolution, m (IDL `rangeRes`).
        range_res: f64,
        /// Scans per second, Hz.
        frequency: f64,
    }

    /// `RTC::RangeData`: one scan of a range sensor (a laser scanner).
    RangeData {
        /// Time stamp.
        tm: Time,
        /// The ranges, m, from `config.min_angle` on.
        ranges: Vec<f64>,
        /// The sensor's geometry.
        geometry: RangerGeometry,
        /// The scan's configuration.
        config: RangerConfig,
    }

    /// `RTC::IntensityData`: one scan's return intensities.
    IntensityData {
        /// Time stamp.
        tm: Time,
        /// The intensities, from `config.min_angle` on.
        intensities: Vec<f64>,
        /// The sensor's geometry.
        geometry: RangerGeometry,
        /// The scan's configuration.
        config: RangerConfig,
    }
);

/// A `Geometry3D` element: nine doubles.
impl CdrElement for Geometry3D {
    const MIN_SIZE: usize = 9 * 8;
}

/// A `PointCloudPoint` element: six doubles.
impl CdrElement for PointCloudPoint {
    const MIN_SIZE: usize = 6 * 8;
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PortData;
    use bytes::{Bytes, BytesMut};

    #[test]
    fn an_enum_beyond_its_last_member_does_not_decode() {
        let mut body = BytesMut::new();
        let state = GripperState {
            tm: Time { sec: 1, nsec: 2 },
            status: GripperStatus::Unknown,
        };
        state.encode(&mut body).unwrap();
        assert_eq!(&body[8..], 3u32.to_le_bytes());
        assert_eq!(GripperState::decode(body.clone().freeze()).unwrap(), state);
        body[8] = 4;
        let refused = GripperState::decode(body.freeze()).unwrap_err();
        assert!(
            refused.to_string().contains("RTC::GripperStatus"),
            "{refused}"
        );
        assert!(GPSData::decode(Bytes::from_static(&[0xff; 96])).is_err());
    }
}
