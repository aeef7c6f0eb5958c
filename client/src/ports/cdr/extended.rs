//! The types of OpenRTM-aist's `ExtendedDataTypes.idl` (module `RTC`)
//! implemented so far: [`Point2D`], [`Pose2D`] and [`Velocity2D`], and the `Timed*`
//! wrappers. Lengths are in metres, angles in radians, time in seconds.

idl_structs!(
    /// `RTC::Point2D`.
    Point2D [Copy] {
        /// X coordinate.
        x: f64,
        /// Y coordinate.
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
);

timed_structs!(
    /// `RTC::TimedPose2D`.
    TimedPose2D(Pose2D) [Copy];
    /// `RTC::TimedVelocity2D`.
    TimedVelocity2D(Velocity2D) [Copy];
);

#[cfg(test)]
mod tests {
    use super::super::testing::{bytes, check, TM, TM_CDR};
    use super::*;

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
}
