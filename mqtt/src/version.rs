//! The protocol versions the codec speaks, named by the level byte of
//! CONNECT, with the protocol name each one carries.

/// An MQTT protocol version, as the level byte of CONNECT names it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ProtocolVersion {
    /// MQTT 3.1 (IBM's, level 3, protocol name `MQIsdp`): decoded and
    /// encoded as 3.1.1, which kept its wire format.
    V3_1,
    /// MQTT 3.1.1 (OASIS, level 4).
    V3_1_1,
    /// MQTT 5.0 (OASIS, level 5).
    V5,
}

impl ProtocolVersion {
    /// The level byte of CONNECT.
    pub fn level(self) -> u8 {
        match self {
            ProtocolVersion::V3_1 => 3,
            ProtocolVersion::V3_1_1 => 4,
            ProtocolVersion::V5 => 5,
        }
    }

    /// The protocol name CONNECT carries with this level.
    pub fn protocol_name(self) -> &'static str {
        match self {
            ProtocolVersion::V3_1 => "MQIsdp",
            ProtocolVersion::V3_1_1 | ProtocolVersion::V5 => "MQTT",
        }
    }

    /// The version a CONNECT's protocol name and level name, if it is one
    /// of these three.
    pub fn from_connect(name: &[u8], level: u8) -> Option<Self> {
        [
            ProtocolVersion::V3_1,
            ProtocolVersion::V3_1_1,
            ProtocolVersion::V5,
        ]
        .into_iter()
        .find(|v| v.level() == level && v.protocol_name().as_bytes() == name)
    }

    /// Whether this is MQTT 5.0, with properties and reason codes.
    pub fn is_v5(self) -> bool {
        self == ProtocolVersion::V5
    }
}
