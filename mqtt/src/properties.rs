//! MQTT 5.0 properties (2.2.2): every identifier of the specification, the
//! packets each may appear on, and [`Properties`], one typed field per
//! property, decoded with duplicates refused (except User Property, and
//! Subscription Identifier on PUBLISH) and values range-checked.

use crate::error::Problem;
use crate::qos::QoS;
use crate::string::MqttString;
use crate::topic::TopicName;
use crate::wire::{
    binary, fail, put_binary, put_string, put_u16, put_u32, put_u8, put_vbi, string, vbi, Counter,
    Fault, PResult, Sink, VBI_MAX,
};
use bytes::Bytes;
use nom::bytes::complete::take;
use nom::number::complete::{be_u16, be_u32, be_u8};
use std::num::{NonZeroU16, NonZeroU32};

/// Where a property list sits: a packet, or the will inside CONNECT.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PropertyContext {
    /// CONNECT's properties.
    Connect,
    /// The will properties in CONNECT's payload.
    Will,
    /// CONNACK.
    ConnAck,
    /// PUBLISH.
    Publish,
    /// PUBACK, PUBREC, PUBREL and PUBCOMP.
    PubResponse,
    /// SUBSCRIBE.
    Subscribe,
    /// SUBACK.
    SubAck,
    /// UNSUBSCRIBE.
    Unsubscribe,
    /// UNSUBACK.
    UnsubAck,
    /// DISCONNECT.
    Disconnect,
    /// AUTH.
    Auth,
}

macro_rules! property_ids {
    ($($(#[$doc:meta])* $variant:ident = $id:literal, [$($ctx:ident),*];)*) => {
        /// A property identifier (MQTT 5.0, 2.2.2.2).
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
        #[repr(u8)]
        pub enum PropertyId {
            $($(#[$doc])* $variant = $id,)*
        }

        impl PropertyId {
            /// The identifier for a number, if 5.0 defines it.
            pub fn from_id(id: u32) -> Option<Self> {
                match id {
                    $($id => Some(PropertyId::$variant),)*
                    _ => None,
                }
            }

            /// Whether the property may appear in `context`.
            pub fn allowed_in(self, context: PropertyContext) -> bool {
                match self {
                    $(PropertyId::$variant => matches!(context, $(PropertyContext::$ctx)|*),)*
                }
            }
        }
    };
}

property_ids! {
    /// 0x01, byte: the payload is UTF-8 (1) or unspecified bytes (0).
    PayloadFormatIndicator = 0x01, [Publish, Will];
    /// 0x02, four byte integer: seconds the message lives.
    MessageExpiryInterval = 0x02, [Publish, Will];
    /// 0x03, UTF-8 string: the payload's content type.
    ContentType = 0x03, [Publish, Will];
    /// 0x08, UTF-8 string: the topic a response goes to.
    ResponseTopic = 0x08, [Publish, Will];
    /// 0x09, binary data: correlates a response with its request.
    CorrelationData = 0x09, [Publish, Will];
    /// 0x0B, variable byte integer: a subscription's identifier.
    SubscriptionIdentifier = 0x0B, [Publish, Subscribe];
    /// 0x11, four byte integer: seconds a session outlives its connection.
    SessionExpiryInterval = 0x11, [Connect, ConnAck, Disconnect];
    /// 0x12, UTF-8 string: the client identifier the server assigned.
    AssignedClientIdentifier = 0x12, [ConnAck];
    /// 0x13, two byte integer: the keep alive the server imposes.
    ServerKeepAlive = 0x13, [ConnAck];
    /// 0x15, UTF-8 string: the extended authentication method.
    AuthenticationMethod = 0x15, [Connect, ConnAck, Auth];
    /// 0x16, binary data: extended authentication data.
    AuthenticationData = 0x16, [Connect, ConnAck, Auth];
    /// 0x17, byte: whether failures may carry reason strings and user properties.
    RequestProblemInformation = 0x17, [Connect];
    /// 0x18, four byte integer: seconds to wait before publishing the will.
    WillDelayInterval = 0x18, [Will];
    /// 0x19, byte: whether the client asks for response information.
    RequestResponseInformation = 0x19, [Connect];
    /// 0x1A, UTF-8 string: the basis of response topics.
    ResponseInformation = 0x1A, [ConnAck];
    /// 0x1C, UTF-8 string: another server to use.
    ServerReference = 0x1C, [ConnAck, Disconnect];
    /// 0x1F, UTF-8 string: a human-readable reason.
    ReasonString = 0x1F, [ConnAck, PubResponse, SubAck, UnsubAck, Disconnect, Auth];
    /// 0x21, two byte integer: QoS 1 and 2 publishes the sender accepts at once.
    ReceiveMaximum = 0x21, [Connect, ConnAck];
    /// 0x22, two byte integer: the highest topic alias the sender accepts.
    TopicAliasMaximum = 0x22, [Connect, ConnAck];
    /// 0x23, two byte integer: a topic alias.
    TopicAlias = 0x23, [Publish];
    /// 0x24, byte: the highest QoS the server supports (0 or 1).
    MaximumQos = 0x24, [ConnAck];
    /// 0x25, byte: whether the server supports retained messages.
    RetainAvailable = 0x25, [ConnAck];
    /// 0x26, UTF-8 string pair: a user property.
    UserProperty = 0x26, [Connect, Will, ConnAck, Publish, PubResponse, Subscribe, SubAck, Unsubscribe, UnsubAck, Disconnect, Auth];
    /// 0x27, four byte integer: the largest packet the sender accepts.
    MaximumPacketSize = 0x27, [Connect, ConnAck];
    /// 0x28, byte: whether the server supports wildcard subscriptions.
    WildcardSubscriptionAvailable = 0x28, [ConnAck];
    /// 0x29, byte: whether the server supports subscription identifiers.
    SubscriptionIdentifierAvailable = 0x29, [ConnAck];
    /// 0x2A, byte: whether the server supports shared subscriptions.
    SharedSubscriptionAvailable = 0x2A, [ConnAck];
}

/// The properties of a packet (or of a will): a handle that holds nothing
/// when there are none, so that packets stay small and a packet without
/// properties allocates nothing; read and set the fields of
/// [`PropertyValues`] through it (the first change allocates).
#[derive(Clone, Default)]
pub struct Properties(Option<Box<PropertyValues>>);

/// The values of the properties, one field per property. Byte properties
/// that can only be 0 or 1 are `bool`s; those whose zero value is forbidden
/// are `NonZero`s.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PropertyValues {
    /// 0x01: `true` if the payload is UTF-8.
    pub payload_format_utf8: Option<bool>,
    /// 0x02.
    pub message_expiry_interval: Option<u32>,
    /// 0x03.
    pub content_type: Option<MqttString>,
    /// 0x08 (a topic name: no wildcards, MQTT-3.3.2-14).
    pub response_topic: Option<TopicName>,
    /// 0x09.
    pub correlation_data: Option<Bytes>,
    /// 0x0B: at most one on SUBSCRIBE, any number on PUBLISH; each 1 to 268,435,455.
    pub subscription_identifiers: Vec<NonZeroU32>,
    /// 0x11.
    pub session_expiry_interval: Option<u32>,
    /// 0x12.
    pub assigned_client_identifier: Option<MqttString>,
    /// 0x13.
    pub server_keep_alive: Option<u16>,
    /// 0x15.
    pub authentication_method: Option<MqttString>,
    /// 0x16 (only with an authentication method).
    pub authentication_data: Option<Bytes>,
    /// 0x17.
    pub request_problem_information: Option<bool>,
    /// 0x18.
    pub will_delay_interval: Option<u32>,
    /// 0x19.
    pub request_response_information: Option<bool>,
    /// 0x1A.
    pub response_information: Option<MqttString>,
    /// 0x1C.
    pub server_reference: Option<MqttString>,
    /// 0x1F.
    pub reason_string: Option<MqttString>,
    /// 0x21.
    pub receive_maximum: Option<NonZeroU16>,
    /// 0x22.
    pub topic_alias_maximum: Option<u16>,
    /// 0x23.
    pub topic_alias: Option<NonZeroU16>,
    /// 0x24: QoS 0 or 1 (a server supporting QoS 2 omits the property).
    pub maximum_qos: Option<QoS>,
    /// 0x25.
    pub retain_available: Option<bool>,
    /// 0x26, in the order sent (the specification keeps order and duplicates).
    pub user_properties: Vec<(MqttString, MqttString)>,
    /// 0x27.
    pub maximum_packet_size: Option<NonZeroU32>,
    /// 0x28.
    pub wildcard_subscription_available: Option<bool>,
    /// 0x29.
    pub subscription_identifier_available: Option<bool>,
    /// 0x2A.
    pub shared_subscription_available: Option<bool>,
}

/// Writes a property's identifier, refusing it where it is not allowed.
fn put_id(s: &mut impl Sink, context: PropertyContext, id: PropertyId) -> Result<(), Fault> {
    if !id.allowed_in(context) {
        return Err(Fault::new(Problem::PropertyNotAllowed(id), ""));
    }
    put_u8(s, id as u8);
    Ok(())
}

/// Stores a property that may appear once.
fn once<T>(slot: &mut Option<T>, value: T, id: PropertyId) -> Result<(), Problem> {
    if slot.is_some() {
        return Err(Problem::DuplicateProperty(id));
    }
    *slot = Some(value);
    Ok(())
}

fn flag(input: &[u8], id: PropertyId) -> PResult<'_, bool> {
    let (rest, byte) = be_u8(input)?;
    match byte {
        0 => Ok((rest, false)),
        1 => Ok((rest, true)),
        _ => fail(Problem::InvalidPropertyValue(id)),
    }
}

fn nonzero_u16(input: &[u8], id: PropertyId) -> PResult<'_, NonZeroU16> {
    let (rest, v) = be_u16(input)?;
    match NonZeroU16::new(v) {
        Some(v) => Ok((rest, v)),
        None => fail(Problem::InvalidPropertyValue(id)),
    }
}

/// What an empty handle reads as.
static NO_PROPERTIES: PropertyValues = PropertyValues {
    payload_format_utf8: None,
    message_expiry_interval: None,
    content_type: None,
    response_topic: None,
    correlation_data: None,
    subscription_identifiers: Vec::new(),
    session_expiry_interval: None,
    assigned_client_identifier: None,
    server_keep_alive: None,
    authentication_method: None,
    authentication_data: None,
    request_problem_information: None,
    will_delay_interval: None,
    request_response_information: None,
    response_information: None,
    server_reference: None,
    reason_string: None,
    receive_maximum: None,
    topic_alias_maximum: None,
    topic_alias: None,
    maximum_qos: None,
    retain_available: None,
    user_properties: Vec::new(),
    maximum_packet_size: None,
    wildcard_subscription_available: None,
    subscription_identifier_available: None,
    shared_subscription_available: None,
};

impl std::ops::Deref for Properties {
    type Target = PropertyValues;

    fn deref(&self) -> &PropertyValues {
        self.0.as_deref().unwrap_or(&NO_PROPERTIES)
    }
}

impl std::ops::DerefMut for Properties {
    fn deref_mut(&mut self) -> &mut PropertyValues {
        self.0.get_or_insert_with(Box::default)
    }
}

impl From<PropertyValues> for Properties {
    fn from(values: PropertyValues) -> Self {
        if values == NO_PROPERTIES {
            Properties(None)
        } else {
            Properties(Some(Box::new(values)))
        }
    }
}

impl PartialEq for Properties {
    fn eq(&self, other: &Self) -> bool {
        **self == **other
    }
}

impl Eq for Properties {}

impl std::fmt::Debug for Properties {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        std::fmt::Debug::fmt(&**self, f)
    }
}

impl Properties {
    /// Whether no property is set.
    pub fn is_empty(&self) -> bool {
        match &self.0 {
            None => true,
            Some(values) => **values == NO_PROPERTIES,
        }
    }

    /// Reads a property length and the properties after it, checking each
    /// against `context`.
    pub(crate) fn decode<'a>(
        src: &Bytes,
        input: &'a [u8],
        context: PropertyContext,
    ) -> PResult<'a, Properties> {
        let (input, len) = vbi(input)?;
        let (rest, mut list) = take(len)(input)?;
        let mut values = PropertyValues::default();
        while !list.is_empty() {
            (list, ()) = values.decode_one(src, list, context)?;
        }
        if values.authentication_data.is_some() && values.authentication_method.is_none() {
            return fail(Problem::AuthDataWithoutMethod);
        }
        Ok((rest, values.into()))
    }

    /// Writes the property length and the properties, checking each
    /// against `context` and the rules a decoder checks.
    pub(crate) fn write(&self, context: PropertyContext, s: &mut impl Sink) -> Result<(), Fault> {
        let mut counter = Counter::default();
        self.write_list(context, &mut counter)?;
        let len = u32::try_from(counter.0)
            .ok()
            .filter(|&len| len <= VBI_MAX)
            .ok_or(Fault::new(Problem::TooLong(counter.0), ""))?;
        put_vbi(s, len);
        self.write_list(context, s)
    }
}

impl PropertyValues {
    fn decode_one<'a>(
        &mut self,
        src: &Bytes,
        input: &'a [u8],
        context: PropertyContext,
    ) -> PResult<'a, ()> {
        use PropertyId as P;
        let (input, number) = vbi(input)?;
        let Some(id) = PropertyId::from_id(number) else {
            return fail(Problem::UnknownProperty(number));
        };
        if !id.allowed_in(context) {
            return fail(Problem::PropertyNotAllowed(id));
        }
        let (rest, stored) = match id {
            P::PayloadFormatIndicator => {
                let (r, v) = flag(input, id)?;
                (r, once(&mut self.payload_format_utf8, v, id))
            }
            P::MessageExpiryInterval => {
                let (r, v) = be_u32(input)?;
                (r, once(&mut self.message_expiry_interval, v, id))
            }
            P::ContentType => {
                let (r, v) = string(src, input)?;
                (r, once(&mut self.content_type, v, id))
            }
            P::ResponseTopic => {
                let (r, v) = string(src, input)?;
                match TopicName::new(v) {
                    Ok(topic) => (r, once(&mut self.response_topic, topic, id)),
                    Err(e) => return fail(Problem::InvalidTopicName(e)),
                }
            }
            P::CorrelationData => {
                let (r, v) = binary(src, input)?;
                (r, once(&mut self.correlation_data, v, id))
            }
            P::SubscriptionIdentifier => {
                let (r, v) = vbi(input)?;
                let Some(v) = NonZeroU32::new(v) else {
                    return fail(Problem::InvalidPropertyValue(id));
                };
                if context == PropertyContext::Subscribe
                    && !self.subscription_identifiers.is_empty()
                {
                    return fail(Problem::DuplicateProperty(id));
                }
                self.subscription_identifiers.push(v);
                (r, Ok(()))
            }
            P::SessionExpiryInterval => {
                let (r, v) = be_u32(input)?;
                (r, once(&mut self.session_expiry_interval, v, id))
            }
            P::AssignedClientIdentifier => {
                let (r, v) = string(src, input)?;
                (r, once(&mut self.assigned_client_identifier, v, id))
            }
            P::ServerKeepAlive => {
                let (r, v) = be_u16(input)?;
                (r, once(&mut self.server_keep_alive, v, id))
            }
            P::AuthenticationMethod => {
                let (r, v) = string(src, input)?;
                (r, once(&mut self.authentication_method, v, id))
            }
            P::AuthenticationData => {
                let (r, v) = binary(src, input)?;
                (r, once(&mut self.authentication_data, v, id))
            }
            P::RequestProblemInformation => {
                let (r, v) = flag(input, id)?;
                (r, once(&mut self.request_problem_information, v, id))
            }
            P::WillDelayInterval => {
                let (r, v) = be_u32(input)?;
                (r, once(&mut self.will_delay_interval, v, id))
            }
            P::RequestResponseInformation => {
                let (r, v) = flag(input, id)?;
                (r, once(&mut self.request_response_information, v, id))
            }
            P::ResponseInformation => {
                let (r, v) = string(src, input)?;
                (r, once(&mut self.response_information, v, id))
            }
            P::ServerReference => {
                let (r, v) = string(src, input)?;
                (r, once(&mut self.server_reference, v, id))
            }
            P::ReasonString => {
                let (r, v) = string(src, input)?;
                (r, once(&mut self.reason_string, v, id))
            }
            P::ReceiveMaximum => {
                let (r, v) = nonzero_u16(input, id)?;
                (r, once(&mut self.receive_maximum, v, id))
            }
            P::TopicAliasMaximum => {
                let (r, v) = be_u16(input)?;
                (r, once(&mut self.topic_alias_maximum, v, id))
            }
            P::TopicAlias => {
                let (r, v) = nonzero_u16(input, id)?;
                (r, once(&mut self.topic_alias, v, id))
            }
            P::MaximumQos => {
                let (r, v) = flag(input, id)?;
                let qos = if v { QoS::AtLeastOnce } else { QoS::AtMostOnce };
                (r, once(&mut self.maximum_qos, qos, id))
            }
            P::RetainAvailable => {
                let (r, v) = flag(input, id)?;
                (r, once(&mut self.retain_available, v, id))
            }
            P::UserProperty => {
                let (r, key) = string(src, input)?;
                let (r, value) = string(src, r)?;
                self.user_properties.push((key, value));
                (r, Ok(()))
            }
            P::MaximumPacketSize => {
                let (r, v) = be_u32(input)?;
                let Some(v) = NonZeroU32::new(v) else {
                    return fail(Problem::InvalidPropertyValue(id));
                };
                (r, once(&mut self.maximum_packet_size, v, id))
            }
            P::WildcardSubscriptionAvailable => {
                let (r, v) = flag(input, id)?;
                (r, once(&mut self.wildcard_subscription_available, v, id))
            }
            P::SubscriptionIdentifierAvailable => {
                let (r, v) = flag(input, id)?;
                (r, once(&mut self.subscription_identifier_available, v, id))
            }
            P::SharedSubscriptionAvailable => {
                let (r, v) = flag(input, id)?;
                (r, once(&mut self.shared_subscription_available, v, id))
            }
        };
        match stored {
            Ok(()) => Ok((rest, ())),
            Err(problem) => fail(problem),
        }
    }

    fn write_list(&self, context: PropertyContext, s: &mut impl Sink) -> Result<(), Fault> {
        use PropertyId as P;
        if let Some(v) = self.payload_format_utf8 {
            put_id(s, context, P::PayloadFormatIndicator)?;
            put_u8(s, u8::from(v));
        }
        if let Some(v) = self.message_expiry_interval {
            put_id(s, context, P::MessageExpiryInterval)?;
            put_u32(s, v);
        }
        if let Some(v) = &self.content_type {
            put_id(s, context, P::ContentType)?;
            put_string(s, v);
        }
        if let Some(v) = &self.response_topic {
            put_id(s, context, P::ResponseTopic)?;
            put_string(s, v.as_mqtt_string());
        }
        if let Some(v) = &self.correlation_data {
            put_id(s, context, P::CorrelationData)?;
            put_binary(s, v, "")?;
        }
        if context == PropertyContext::Subscribe && self.subscription_identifiers.len() > 1 {
            return Err(Fault::new(
                Problem::DuplicateProperty(P::SubscriptionIdentifier),
                "",
            ));
        }
        for v in &self.subscription_identifiers {
            put_id(s, context, P::SubscriptionIdentifier)?;
            if v.get() > VBI_MAX {
                return Err(Fault::new(
                    Problem::InvalidPropertyValue(P::SubscriptionIdentifier),
                    "",
                ));
            }
            put_vbi(s, v.get());
        }
        if let Some(v) = self.session_expiry_interval {
            put_id(s, context, P::SessionExpiryInterval)?;
            put_u32(s, v);
        }
        if let Some(v) = &self.assigned_client_identifier {
            put_id(s, context, P::AssignedClientIdentifier)?;
            put_string(s, v);
        }
        if let Some(v) = self.server_keep_alive {
            put_id(s, context, P::ServerKeepAlive)?;
            put_u16(s, v);
        }
        if let Some(v) = &self.authentication_method {
            put_id(s, context, P::AuthenticationMethod)?;
            put_string(s, v);
        }
        if let Some(v) = &self.authentication_data {
            if self.authentication_method.is_none() {
                return Err(Fault::new(Problem::AuthDataWithoutMethod, ""));
            }
            put_id(s, context, P::AuthenticationData)?;
            put_binary(s, v, "")?;
        }
        if let Some(v) = self.request_problem_information {
            put_id(s, context, P::RequestProblemInformation)?;
            put_u8(s, u8::from(v));
        }
        if let Some(v) = self.will_delay_interval {
            put_id(s, context, P::WillDelayInterval)?;
            put_u32(s, v);
        }
        if let Some(v) = self.request_response_information {
            put_id(s, context, P::RequestResponseInformation)?;
            put_u8(s, u8::from(v));
        }
        if let Some(v) = &self.response_information {
            put_id(s, context, P::ResponseInformation)?;
            put_string(s, v);
        }
        if let Some(v) = &self.server_reference {
            put_id(s, context, P::ServerReference)?;
            put_string(s, v);
        }
        if let Some(v) = &self.reason_string {
            put_id(s, context, P::ReasonString)?;
            put_string(s, v);
        }
        if let Some(v) = self.receive_maximum {
            put_id(s, context, P::ReceiveMaximum)?;
            put_u16(s, v.get());
        }
        if let Some(v) = self.topic_alias_maximum {
            put_id(s, context, P::TopicAliasMaximum)?;
            put_u16(s, v);
        }
        if let Some(v) = self.topic_alias {
            put_id(s, context, P::TopicAlias)?;
            put_u16(s, v.get());
        }
        if let Some(v) = self.maximum_qos {
            put_id(s, context, P::MaximumQos)?;
            if v == QoS::ExactlyOnce {
                return Err(Fault::new(Problem::InvalidPropertyValue(P::MaximumQos), ""));
            }
            put_u8(s, v.level());
        }
        if let Some(v) = self.retain_available {
            put_id(s, context, P::RetainAvailable)?;
            put_u8(s, u8::from(v));
        }
        for (key, value) in &self.user_properties {
            put_id(s, context, P::UserProperty)?;
            put_string(s, key);
            put_string(s, value);
        }
        if let Some(v) = self.maximum_packet_size {
            put_id(s, context, P::MaximumPacketSize)?;
            put_u32(s, v.get());
        }
        if let Some(v) = self.wildcard_subscription_available {
            put_id(s, context, P::WildcardSubscriptionAvailable)?;
            put_u8(s, u8::from(v));
        }
        if let Some(v) = self.subscription_identifier_available {
            put_id(s, context, P::SubscriptionIdentifierAvailable)?;
            put_u8(s, u8::from(v));
        }
        if let Some(v) = self.shared_subscription_available {
            put_id(s, context, P::SharedSubscriptionAvailable)?;
            put_u8(s, u8::from(v));
        }
        Ok(())
    }
}
