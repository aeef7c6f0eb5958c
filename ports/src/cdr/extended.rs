//! The types of OpenRTM-aist's `ExtendedDataTypes.idl` (module `RTC`),
//! every one: the geometry structs in 2D and 3D (points, vectors, poses,
//! velocities, accelerations, sizes, covariances, control commands),
//! [`RGBColour`], [`OAP`] and [`Quaternion`], and their `Timed*` wrappers.
//! All their members are `double`s or structs of `double`s; lengths are in
//! metres, angles in radians, time in seconds.

idl_structs!(
    /// `RTC::RGBColour`: each channel from 0.0 (none) to 1.0 (full).
    RGBColour [Copy] {
        /// Red.
        r: f64,
        /// Green.
        g: f64,
        /// Blue.
        b: f64,
    }

    /// `RTC::Point2D`.
    Point2D [Copy] {
        /// X coordinate.
        x: f64,
        /// Y coordinate.
        y: f64,
    }

    /// `RTC::Vector2D`.
    Vector2D [Copy] {
        /// X component.
        x: f64,
        /// Y component.
        y: f64,
    }

    /// `RTC::Pose2D`.
    Pose2D [Copy] {
        /// Position.
        position: Point2D,
        /// Heading.
        heading: f64,
    }

    /// `RTC::Velocity2D`.
    Velocity2D [Copy] {
        /// Along x, m/s.
        vx: f64,
        /// Along y, m/s.
        vy: f64,
        /// Yaw rate, rad/s.
        va: f64,
    }

    /// `RTC::Acceleration2D`.
    Acceleration2D [Copy] {
        /// Along x, m/s².
        ax: f64,
        /// Along y, m/s².
        ay: f64,
    }

    /// `RTC::PoseVel2D`.
    PoseVel2D [Copy] {
        /// Pose.
        pose: Pose2D,
        /// Velocities.
        velocities: Velocity2D,
    }

    /// `RTC::Size2D`.
    Size2D [Copy] {
        /// Length.
        l: f64,
        /// Width.
        w: f64,
    }

    /// `RTC::Geometry2D`: where a device is on its parent (e.g. the robot)
    /// and how large it is.
    Geometry2D [Copy] {
        /// Pose of the device's base point in its parent's frame.
        pose: Pose2D,
        /// Size, from the base point.
        size: Size2D,
    }

    /// `RTC::Covariance2D`: the upper triangle of a 2D pose's covariance
    /// (x, y, theta).
    Covariance2D [Copy] {
        /// (0, 0).
        xx: f64,
        /// (0, 1).
        xy: f64,
        /// (0, 2).
        xt: f64,
        /// (1, 1).
        yy: f64,
        /// (1, 2).
        yt: f64,
        /// (2, 2).
        tt: f64,
    }

    /// `RTC::PointCovariance2D`: the upper triangle of a 2D point's
    /// covariance.
    PointCovariance2D [Copy] {
        /// (0, 0).
        xx: f64,
        /// (0, 1).
        xy: f64,
        /// (1, 1).
        yy: f64,
    }

    /// `RTC::Carlike`: a car-like robot's command.
    Carlike [Copy] {
        /// Speed, m/s.
        speed: f64,
        /// Steering angle (IDL `steeringAngle`).
        steering_angle: f64,
    }

    /// `RTC::SpeedHeading2D`: a command to move in a direction in 2D.
    SpeedHeading2D [Copy] {
        /// Speed, m/s.
        speed: f64,
        /// Direction of travel from the x axis.
        heading: f64,
    }

    /// `RTC::Point3D`.
    Point3D [Copy] {
        /// X coordinate.
        x: f64,
        /// Y coordinate.
        y: f64,
        /// Z coordinate.
        z: f64,
    }

    /// `RTC::Vector3D`.
    Vector3D [Copy] {
        /// X component.
        x: f64,
        /// Y component.
        y: f64,
        /// Z component.
        z: f64,
    }

    /// `RTC::Orientation3D`: roll, pitch, yaw.
    Orientation3D [Copy] {
        /// Roll.
        r: f64,
        /// Pitch.
        p: f64,
        /// Yaw.
        y: f64,
    }

    /// `RTC::Pose3D`.
    Pose3D [Copy] {
        /// Position.
        position: Point3D,
        /// Orientation.
        orientation: Orientation3D,
    }

    /// `RTC::Velocity3D`.
    Velocity3D [Copy] {
        /// Along x, m/s.
        vx: f64,
        /// Along y, m/s.
        vy: f64,
        /// Along z, m/s.
        vz: f64,
        /// Roll rate, rad/s.
        vr: f64,
        /// Pitch rate, rad/s.
        vp: f64,
        /// Yaw rate, rad/s.
        va: f64,
    }

    /// `RTC::AngularVelocity3D`.
    AngularVelocity3D [Copy] {
        /// About x, rad/s.
        avx: f64,
        /// About y, rad/s.
        avy: f64,
        /// About z, rad/s.
        avz: f64,
    }

    /// `RTC::Acceleration3D`.
    Acceleration3D [Copy] {
        /// Along x, m/s².
        ax: f64,
        /// Along y, m/s².
        ay: f64,
        /// Along z, m/s².
        az: f64,
    }

    /// `RTC::AngularAcceleration3D`.
    AngularAcceleration3D [Copy] {
        /// About x, rad/s².
        aax: f64,
        /// About y, rad/s².
        aay: f64,
        /// About z, rad/s².
        aaz: f64,
    }

    /// `RTC::PoseVel3D`.
    PoseVel3D [Copy] {
        /// Pose.
        pose: Pose3D,
        /// Velocities.
        velocities: Velocity3D,
    }

    /// `RTC::Size3D`.
    Size3D [Copy] {
        /// Length.
        l: f64,
        /// Width.
        w: f64,
        /// Height.
        h: f64,
    }

    /// `RTC::Geometry3D`: where a device is on its parent (e.g. the robot)
    /// and how large it is.
    Geometry3D [Copy] {
        /// Pose of the device's base point in its parent's frame.
        pose: Pose3D,
        /// Size, from the base point.
        size: Size3D,
    }

    /// `RTC::Covariance3D`: the upper triangle of a 3D pose's covariance
    /// (x, y, z, roll, pitch, yaw), row by row.
    Covariance3D [Copy] {
        /// (0, 0).
        xx: f64,
        /// (0, 1).
        xy: f64,
        /// (0, 2).
        xz: f64,
        /// (0, 3).
        xr: f64,
        /// (0, 4).
        xp: f64,
        /// (0, 5).
        xa: f64,
        /// (1, 1).
        yy: f64,
        /// (1, 2).
        yz: f64,
        /// (1, 3).
        yr: f64,
        /// (1, 4).
        yp: f64,
        /// (1, 5).
        ya: f64,
        /// (2, 2).
        zz: f64,
        /// (2, 3).
        zr: f64,
        /// (2, 4).
        zp: f64,
        /// (2, 5).
        za: f64,
        /// (3, 3).
        rr: f64,
        /// (3, 4).
        rp: f64,
        /// (3, 5).
        ra: f64,
        /// (4, 4).
        pp: f64,
        /// (4, 5).
        pa: f64,
        /// (5, 5).
        aa: f64,
    }

    /// `RTC::SpeedHeading3D`: a command to move in a direction in 3D.
    SpeedHeading3D [Copy] {
        /// Speed, m/s.
        speed: f64,
        /// Direction of travel.
        direction: Orientation3D,
    }

    /// `RTC::OAP`: orientation, approach and position vectors.
    OAP [Copy] {
        /// Orientation vector.
        orientation: Vector3D,
        /// Approach vector.
        approach: Vector3D,
        /// Position vector.
        position: Vector3D,
    }

    /// `RTC::Quaternion`.
    Quaternion [Copy] {
        /// X component.
        x: f64,
        /// Y component.
        y: f64,
        /// Z component.
        z: f64,
        /// W (scalar) component.
        w: f64,
    }
);

timed_structs!(
    /// `RTC::TimedRGBColour`.
    TimedRGBColour(RGBColour) [Copy];
    /// `RTC::TimedPoint2D`.
    TimedPoint2D(Point2D) [Copy];
    /// `RTC::TimedVector2D`.
    TimedVector2D(Vector2D) [Copy];
    /// `RTC::TimedPose2D`.
    TimedPose2D(Pose2D) [Copy];
    /// `RTC::TimedVelocity2D`.
    TimedVelocity2D(Velocity2D) [Copy];
    /// `RTC::TimedAcceleration2D`.
    TimedAcceleration2D(Acceleration2D) [Copy];
    /// `RTC::TimedPoseVel2D`.
    TimedPoseVel2D(PoseVel2D) [Copy];
    /// `RTC::TimedSize2D`.
    TimedSize2D(Size2D) [Copy];
    /// `RTC::TimedGeometry2D`.
    TimedGeometry2D(Geometry2D) [Copy];
    /// `RTC::TimedCovariance2D`.
    TimedCovariance2D(Covariance2D) [Copy];
    /// `RTC::TimedPointCovariance2D`.
    TimedPointCovariance2D(PointCovariance2D) [Copy];
    /// `RTC::TimedCarlike`.
    TimedCarlike(Carlike) [Copy];
    /// `RTC::TimedSpeedHeading2D`.
    TimedSpeedHeading2D(SpeedHeading2D) [Copy];
    /// `RTC::TimedPoint3D`.
    TimedPoint3D(Point3D) [Copy];
    /// `RTC::TimedVector3D`.
    TimedVector3D(Vector3D) [Copy];
    /// `RTC::TimedOrientation3D`.
    TimedOrientation3D(Orientation3D) [Copy];
    /// `RTC::TimedPose3D`.
    TimedPose3D(Pose3D) [Copy];
    /// `RTC::TimedVelocity3D`.
    TimedVelocity3D(Velocity3D) [Copy];
    /// `RTC::TimedAngularVelocity3D`.
    TimedAngularVelocity3D(AngularVelocity3D) [Copy];
    /// `RTC::TimedAcceleration3D`.
    TimedAcceleration3D(Acceleration3D) [Copy];
    /// `RTC::TimedAngularAcceleration3D`.
    TimedAngularAcceleration3D(AngularAcceleration3D) [Copy];
    /// `RTC::TimedPoseVel3D`.
    TimedPoseVel3D(PoseVel3D) [Copy];
    /// `RTC::TimedSize3D`.
    TimedSize3D(Size3D) [Copy];
    /// `RTC::TimedGeometry3D`.
    TimedGeometry3D(Geometry3D) [Copy];
    /// `RTC::TimedCovariance3D`.
    TimedCovariance3D(Covariance3D) [Copy];
    /// `RTC::TimedSpeedHeading3D`.
    TimedSpeedHeading3D(SpeedHeading3D) [Copy];
    /// `RTC::TimedOAP`.
    TimedOAP(OAP) [Copy];
    /// `RTC::TimedQuaternion`.
    TimedQuaternion(Quaternion) [Copy];
);

#[cfg(test)]
mod tests {
    use super::super::testing::{bytes, check, TM, TM_CDR};
    use super::*;
    use crate::{DataError, PortData};
    use bytes::Bytes;

    /// `values` as little-endian doubles after `TM`.
    fn timed_doubles(values: impl IntoIterator<Item = f64>) -> Vec<u8> {
        let mut body = TM_CDR.to_vec();
        for value in values {
            body.extend_from_slice(&value.to_le_bytes());
        }
        body
    }

    #[test]
    fn timed_pose_2d() {
        let value = TimedPose2D {
            tm: TM,
            data: Pose2D {
                position: Point2D { x: 1.0, y: 2.0 },
                heading: -2.0,
            },
        };
        check(
            value,
            &bytes(&[
                &TM_CDR,
                &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],
                &[0, 0, 0, 0, 0, 0, 0x00, 0x40],
                &[0, 0, 0, 0, 0, 0, 0x00, 0xc0],
            ]),
        );
    }

    #[test]
    fn timed_velocity_2d() {
        let value = TimedVelocity2D {
            tm: TM,
            data: Velocity2D {
                vx: 2.0,
                vy: 1.0,
                va: -2.0,
            },
        };
        check(
            value,
            &bytes(&[
                &TM_CDR,
                &[0, 0, 0, 0, 0, 0, 0x00, 0x40],
                &[0, 0, 0, 0, 0, 0, 0xf0, 0x3f],
                &[0, 0, 0, 0, 0, 0, 0x00, 0xc0],
            ]),
        );
    }

    #[test]
    fn nested_structs_are_their_members_in_idl_order() {
        let value = TimedPoseVel3D {
            tm: TM,
            data: PoseVel3D {
                pose: Pose3D {
                    position: Point3D {
                        x: 1.0,
                        y: 2.0,
                        z: 3.0,
                    },
                    orientation: Orientation3D {
                        r: 4.0,
                        p: 5.0,
                        y: 6.0,
                    },
                },
                velocities: Velocity3D {
                    vx: 7.0,
                    vy: 8.0,
                    vz: 9.0,
                    vr: 10.0,
                    vp: 11.0,
                    va: 12.0,
                },
            },
        };
        check(value, &timed_doubles((1..=12).map(f64::from)));
    }

    #[test]
    fn covariance_3d_is_its_upper_triangle_row_by_row() {
        let data = Covariance3D {
            xx: 1.0,
            xy: 2.0,
            xz: 3.0,
            xr: 4.0,
            xp: 5.0,
            xa: 6.0,
            yy: 7.0,
            yz: 8.0,
            yr: 9.0,
            yp: 10.0,
            ya: 11.0,
            zz: 12.0,
            zr: 13.0,
            zp: 14.0,
            za: 15.0,
            rr: 16.0,
            rp: 17.0,
            ra: 18.0,
            pp: 19.0,
            pa: 20.0,
            aa: 21.0,
        };
        check(
            TimedCovariance3D { tm: TM, data },
            &timed_doubles((1..=21).map(f64::from)),
        );
        assert_eq!(
            TimedCovariance3D::TYPE_NAME,
            Some("IDL:RTC/TimedCovariance3D:1.0")
        );
        assert_eq!(OAP::TYPE_NAME, Some("IDL:RTC/OAP:1.0"));
    }

    #[test]
    fn any_bytes_of_another_length_are_refused_without_panic() {
        // TimedOAP is 8 + 9 * 8 bytes; every bit pattern is some double
        // (NaNs included), so only the length can be wrong.
        let len = 8 + 9 * 8;
        for n in (0..len).chain([len + 1, len + 8, 4096]) {
            let garbage = Bytes::from(vec![0xa5; n]);
            assert!(TimedOAP::decode(garbage).is_err(), "{n} bytes");
        }
        let garbage = Bytes::from(vec![0xff; len]);
        let value = TimedOAP::decode(garbage).unwrap();
        assert!(value.data.position.z.is_nan());
        assert!(matches!(
            TimedOAP::decode(Bytes::from(vec![0; len - 3])),
            Err(DataError::Truncated {
                offset: 72,
                needed: 3
            })
        ));
    }
}
