//! rmw_zenoh's names on the wire: a topic's data key expression, the liveliness tokens that
//! announce a node and its publishers and subscriptions (what `ros2 node list`, `ros2 topic list`
//! and rviz2's topic picker read), the publisher id derived from its token, and the attachment
//! every sample carries. The layout is rmw_zenoh's design document's and its source's
//! (`liveliness_utils.cpp`, `attachment_helpers.cpp`), for Jazzy from 0.2.4 and Kilted.

use super::RosType;

/// The admin space every rmw_zenoh liveliness token lives in.
pub const LIVELINESS_PREFIX: &str = "@ros2_lv";

/// Why a name cannot be a ROS 2 topic.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    /// Not a fully qualified ROS 2 name.
    #[error(
        "{0:?} is not a ROS 2 topic name: it starts with '/' and has tokens of letters, digits and '_' (not starting with a digit) separated by single '/'"
    )]
    Topic(String),
}

/// A fully qualified topic name (`/map`, `/robot1/path`), checked against ROS 2's rules.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct TopicName(String);

impl TopicName {
    /// `name` if it is a fully qualified ROS 2 topic name.
    pub fn new(name: &str) -> Result<Self, NameError> {
        let token_ok = |t: &str| {
            !t.is_empty()
                && !t.starts_with(|c: char| c.is_ascii_digit())
                && t.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        };
        match name.strip_prefix('/') {
            Some(rest) if rest.split('/').all(token_ok) => Ok(TopicName(name.to_owned())),
            _ => Err(NameError::Topic(name.to_owned())),
        }
    }

    /// The name as given.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for TopicName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// The data key expression of `topic` carrying `ty` in `domain`:
/// `DOMAIN/TOPIC/DDS_TYPE/TYPE_HASH`, the topic's leading slash removed and its inner ones kept.
pub fn topic_key(domain: u32, topic: &TopicName, ty: &RosType) -> String {
    format!("{domain}/{}/{}/{}", topic.0.trim_start_matches('/'), ty.dds, ty.hash)
}

/// A key expression that matches `topic` in `domain` whatever type it carries (a subscriber that
/// checks the type itself, or says what it found).
pub fn topic_key_any_type(domain: u32, topic: &TopicName) -> String {
    format!("{domain}/{}/*/*", topic.0.trim_start_matches('/'))
}

/// How a publisher or subscription delivers, as rmw_zenoh writes it into its liveliness token.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Qos {
    /// Reliable (else best effort).
    pub reliable: bool,
    /// Transient local: late subscribers get the last `depth` samples (else volatile).
    pub transient_local: bool,
    /// History depth (keep last).
    pub depth: u32,
}

impl Qos {
    /// Reliable, volatile, keep last 10: ROS 2's default for a topic.
    pub const DEFAULT: Qos = Qos { reliable: true, transient_local: false, depth: 10 };
    /// Reliable, transient local, keep last 1: a map a late subscriber still gets.
    pub const LATCHED: Qos = Qos { reliable: true, transient_local: true, depth: 1 };
    /// Best effort, volatile, keep last 5: ROS 2's sensor-data profile.
    pub const SENSOR_DATA: Qos = Qos { reliable: false, transient_local: false, depth: 5 };

    /// The token's QoS field: `RELIABILITY:DURABILITY:HISTORY,DEPTH:DEADLINE:LIFESPAN:LIVELINESS`,
    /// each slot empty where it holds rmw_zenoh's default (reliable, volatile, keep last 42,
    /// infinite deadline and lifespan, automatic liveliness); reliability 2 is best effort,
    /// durability 1 transient local.
    pub fn keyexpr(&self) -> String {
        let reliability = if self.reliable { "" } else { "2" };
        let durability = if self.transient_local { "1" } else { "" };
        let depth = match self.depth {
            0 | 42 => String::new(),
            d => d.to_string(),
        };
        format!("{reliability}:{durability}:,{depth}:,:,:,,")
    }
}

/// A node as rmw_zenoh announces it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Node {
    /// ROS domain id.
    pub domain: u32,
    /// The zenoh session's id, as zenoh prints it (lowercase hex).
    pub zid: String,
    /// The node's id within its session.
    pub id: u64,
    /// Namespace (`/` for none).
    pub namespace: String,
    /// Node name.
    pub name: String,
}

/// What a token announces besides its node.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EntityKind {
    /// A publisher (`MP`).
    Publisher,
    /// A subscription (`MS`).
    Subscription,
}

impl Node {
    /// The node's own liveliness token: `@ros2_lv/DOMAIN/ZID/ID/ID/NN/ENCLAVE/NAMESPACE/NAME`,
    /// every `/` inside a field written `%` (the enclave is `/`).
    pub fn token(&self) -> String {
        format!(
            "{}/{}/{}/{}/{}/NN/%/{}/{}",
            LIVELINESS_PREFIX,
            self.domain,
            self.zid,
            self.id,
            self.id,
            mangle(&self.namespace),
            mangle(&self.name)
        )
    }

    /// The liveliness token of entity `entity` of this node on `topic`: the node's fields, the
    /// entity's id and kind, then the topic, its type, type hash and QoS.
    pub fn entity_token(&self, entity: u64, kind: EntityKind, topic: &TopicName, ty: &RosType, qos: &Qos) -> String {
        let kind = match kind {
            EntityKind::Publisher => "MP",
            EntityKind::Subscription => "MS",
        };
        format!(
            "{}/{}/{}/{}/{entity}/{kind}/%/{}/{}/{}/{}/{}/{}",
            LIVELINESS_PREFIX,
            self.domain,
            self.zid,
            self.id,
            mangle(&self.namespace),
            mangle(&self.name),
            mangle(topic.as_str()),
            ty.dds,
            ty.hash,
            qos.keyexpr()
        )
    }
}

/// A name inside a token: `/` written `%`.
fn mangle(name: &str) -> String {
    name.replace('/', "%")
}

/// A publisher's id (its GID): the first 16 bytes of the XXH3-128 hash of its liveliness token,
/// the low 64 bits first, each little endian, as rmw_zenoh copies the hash into its GID.
pub fn gid(token: &str) -> [u8; 16] {
    let hash = xxhash_rust::xxh3::xxh3_128(token.as_bytes());
    let mut gid = [0u8; 16];
    gid[..8].copy_from_slice(&(hash as u64).to_le_bytes());
    gid[8..].copy_from_slice(&((hash >> 64) as u64).to_le_bytes());
    gid
}

/// What every sample of an rmw_zenoh publisher carries beside its payload: a subscriber drops a
/// sample without it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Attachment {
    /// The publisher's sample count, from 1.
    pub sequence: i64,
    /// Source time, nanoseconds since the Unix epoch.
    pub source_time_ns: i64,
    /// The publisher's id ([`gid`]).
    pub gid: [u8; 16],
}

/// Why an attachment was not rmw_zenoh's.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("attachment of {0} bytes is not rmw_zenoh's (8-byte sequence, 8-byte time, 16, 16-byte id: 33 bytes)")]
pub struct AttachmentError(pub usize);

impl Attachment {
    /// Its bytes as zenoh-ext's serializer writes `(i64, i64, [u8; 16])`: both integers little
    /// endian, the array behind its LEB128 length (one byte, 16): 33 bytes.
    pub fn to_bytes(&self) -> [u8; 33] {
        let mut out = [0u8; 33];
        out[..8].copy_from_slice(&self.sequence.to_le_bytes());
        out[8..16].copy_from_slice(&self.source_time_ns.to_le_bytes());
        out[16] = 16;
        out[17..].copy_from_slice(&self.gid);
        out
    }

    /// Reads [`Attachment::to_bytes`]'s layout back.
    pub fn parse(bytes: &[u8]) -> Result<Self, AttachmentError> {
        if bytes.len() != 33 || bytes[16] != 16 {
            return Err(AttachmentError(bytes.len()));
        }
        let word = |at: usize| i64::from_le_bytes(bytes[at..at + 8].try_into().expect("8 bytes"));
        Ok(Attachment { sequence: word(0), source_time_ns: word(8), gid: bytes[17..].try_into().expect("16 bytes") })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::{POINT_CLOUD2, STRING};

    #[test]
    fn keys_are_laid_out_as_rmw_zenohs_design_shows_them() {
        // rmw_zenoh's design document: a String publisher on /chatter in domain 0, and on
        // /robot1/chatter (inner slashes kept).
        let chatter = TopicName::new("/chatter").unwrap();
        assert_eq!(
            topic_key(0, &chatter, &STRING),
            "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
        );
        let nested = TopicName::new("/robot1/chatter").unwrap();
        assert!(topic_key(0, &nested, &STRING).starts_with("0/robot1/chatter/std_msgs::msg::dds_::String_/"));
        // Reliable, volatile, depth 7: the document's example QoS.
        assert_eq!(Qos { reliable: true, transient_local: false, depth: 7 }.keyexpr(), "::,7:,:,:,,");
        assert_eq!(Qos::LATCHED.keyexpr(), ":1:,1:,:,:,,");
        assert_eq!(Qos::SENSOR_DATA.keyexpr(), "2::,5:,:,:,,");
        let node = Node {
            domain: 0,
            zid: "aac3178e146ba6f1fc6e6a4085e77f21".into(),
            id: 0,
            namespace: "/".into(),
            name: "emr_station".into(),
        };
        assert_eq!(node.token(), "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/emr_station");
        let map = TopicName::new("/emr/demo/map").unwrap();
        assert_eq!(
            node.entity_token(5, EntityKind::Publisher, &map, &POINT_CLOUD2, &Qos::LATCHED),
            "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/5/MP/%/%/emr_station/%emr%demo%map/\
             sensor_msgs::msg::dds_::PointCloud2_/RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5/:1:,1:,:,:,,"
        );
    }

    #[test]
    fn only_fully_qualified_names_are_topics() {
        for good in ["/map", "/robot1/path", "/a_b/c9"] {
            assert!(TopicName::new(good).is_ok(), "{good}");
        }
        for bad in ["", "/", "map", "/map/", "//map", "/9map", "/ma p", "/ma-p", "/a/*"] {
            assert!(TopicName::new(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn an_attachment_is_33_bytes_and_reads_back() {
        let a = Attachment { sequence: 1, source_time_ns: 1_764_633_600_123_456_789, gid: gid("a token") };
        let bytes = a.to_bytes();
        assert_eq!(&bytes[..8], &1i64.to_le_bytes());
        assert_eq!(bytes[16], 16);
        assert_eq!(Attachment::parse(&bytes), Ok(a));
        assert_eq!(Attachment::parse(&bytes[..32]), Err(AttachmentError(32)));
        assert_ne!(gid("a token"), gid("another token"));
    }
}
