//! ROS 2 topics over rmw_zenoh, with no bridge: a node announced by its liveliness tokens,
//! publishers whose samples carry the attachment rmw_zenoh subscribers require, and the
//! announcement of a subscription. Names, payloads and the attachment's layout are
//! [`proto::ros2`]'s; this module puts them on a session.
//!
//! A transient-local publisher is what rmw_zenoh makes of one: a zenoh-ext advanced publisher
//! whose cache late subscribers (rviz2 opening a map topic) query, found through its own token.

use std::marker::PhantomData;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use proto::ros2::RosType;
use proto::ros2::keys::{Attachment, EntityKind, Node, Qos, TopicName, gid, topic_key};
use proto::ros2::messages::{CdrError, to_cdr};
use serde::Serialize;
use zenoh::Session;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Publisher;
use zenoh::qos::{CongestionControl, Reliability};
use zenoh_ext::{AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

/// Why a ROS 2 entity could not be declared or a message published.
#[derive(Debug, thiserror::Error)]
pub enum Ros2Error {
    /// Zenoh refused a declaration.
    #[error("cannot declare the ROS 2 {what} {key}: {message}")]
    Declare {
        /// What was declared.
        what: &'static str,
        /// Its key expression.
        key: String,
        /// What zenoh said.
        message: String,
    },
    /// A message did not serialise.
    #[error("ROS 2 topic {topic}: {source}")]
    Encode {
        /// The topic.
        topic: String,
        /// Why.
        source: CdrError,
    },
    /// A sample could not be sent.
    #[error("ROS 2 topic {topic}: cannot publish: {message}")]
    Put {
        /// The topic.
        topic: String,
        /// What zenoh said.
        message: String,
    },
}

/// How often a transient-local publisher announces its last sequence number, so that a
/// subscriber that missed a sample asks the cache for it (rmw_zenoh's period).
const HEARTBEAT: Duration = Duration::from_millis(500);

/// A ROS 2 node on a zenoh session, seen by `ros2 node list` while it lives.
pub struct Ros2Node {
    session: Session,
    node: Node,
    /// rmw_zenoh numbers a context's node and its entities from one counter: the node is 0.
    next_entity: AtomicU64,
    _token: LivelinessToken,
}

impl Ros2Node {
    /// Declares node `name` in `namespace` (`/` for none) of ROS domain `domain` on `session`.
    pub async fn new(session: &Session, domain: u32, namespace: &str, name: &str) -> Result<Self, Ros2Error> {
        let node = Node {
            domain,
            zid: session.zid().to_string(),
            id: 0,
            namespace: namespace.to_owned(),
            name: name.to_owned(),
        };
        let token = declare_token(session, node.token(), "node").await?;
        Ok(Ros2Node { session: session.clone(), node, next_entity: AtomicU64::new(1), _token: token })
    }

    /// The ROS domain.
    pub fn domain(&self) -> u32 {
        self.node.domain
    }

    /// A publisher of `M` (whose CDR layout is `ty`'s) on `topic`, announced with `qos`.
    pub async fn publisher<M: Serialize>(
        &self,
        topic: &TopicName,
        ty: RosType,
        qos: Qos,
    ) -> Result<Ros2Publisher<M>, Ros2Error> {
        let entity = self.next_entity.fetch_add(1, Ordering::Relaxed);
        let token_key = self.node.entity_token(entity, EntityKind::Publisher, topic, &ty, &qos);
        let key = topic_key(self.node.domain, topic, &ty);
        let declare =
            |e: zenoh::Error| Ros2Error::Declare { what: "publisher", key: key.clone(), message: e.to_string() };
        let reliability = if qos.reliable { Reliability::Reliable } else { Reliability::BestEffort };
        // Keep-last history drops rather than blocks on congestion, as rmw_zenoh does: a slow
        // subscriber must not stall the station.
        let builder = self
            .session
            .declare_publisher(key.clone())
            .reliability(reliability)
            .congestion_control(CongestionControl::Drop);
        let sink = if qos.transient_local {
            let depth = qos.depth.max(1) as usize;
            Sink::Latched(
                builder
                    .cache(CacheConfig::default().max_samples(depth))
                    .publisher_detection()
                    .sample_miss_detection(MissDetectionConfig::default().sporadic_heartbeat(HEARTBEAT))
                    .await
                    .map_err(declare)?,
            )
        } else {
            Sink::Volatile(builder.await.map_err(declare)?)
        };
        let gid = gid(&token_key);
        let token = declare_token(&self.session, token_key, "publisher").await?;
        Ok(Ros2Publisher {
            topic: topic.clone(),
            sink,
            gid,
            sequence: AtomicI64::new(0),
            _token: token,
            _message: PhantomData,
        })
    }

    /// Announces a subscription of this node to `topic` (what `ros2 topic info` counts and what a
    /// publisher waiting for subscribers sees); it lasts as long as the token.
    pub async fn announce_subscription(
        &self,
        topic: &TopicName,
        ty: RosType,
        qos: Qos,
    ) -> Result<LivelinessToken, Ros2Error> {
        let entity = self.next_entity.fetch_add(1, Ordering::Relaxed);
        let key = self.node.entity_token(entity, EntityKind::Subscription, topic, &ty, &qos);
        declare_token(&self.session, key, "subscription").await
    }
}

async fn declare_token(session: &Session, key: String, what: &'static str) -> Result<LivelinessToken, Ros2Error> {
    session.liveliness().declare_token(key.clone()).await.map_err(|e| Ros2Error::Declare {
        what,
        key,
        message: e.to_string(),
    })
}

enum Sink {
    Volatile(Publisher<'static>),
    Latched(AdvancedPublisher<'static>),
}

/// A publisher of ROS 2 messages `M`: each sample the CDR payload and rmw_zenoh's attachment.
pub struct Ros2Publisher<M> {
    topic: TopicName,
    sink: Sink,
    gid: [u8; 16],
    sequence: AtomicI64,
    _token: LivelinessToken,
    _message: PhantomData<fn(&M)>,
}

impl<M: Serialize> Ros2Publisher<M> {
    /// Publishes `message`.
    pub async fn put(&self, message: &M) -> Result<(), Ros2Error> {
        let payload = to_cdr(message).map_err(|source| Ros2Error::Encode { topic: self.topic.to_string(), source })?;
        let attachment = Attachment {
            sequence: self.sequence.fetch_add(1, Ordering::Relaxed) + 1,
            source_time_ns: now_ns(),
            gid: self.gid,
        }
        .to_bytes()
        .to_vec();
        let sent = match &self.sink {
            Sink::Volatile(p) => p.put(payload).attachment(attachment).await,
            Sink::Latched(p) => p.put(payload).attachment(attachment).await,
        };
        sent.map_err(|e| Ros2Error::Put { topic: self.topic.to_string(), message: e.to_string() })
    }

    /// The topic.
    pub fn topic(&self) -> &TopicName {
        &self.topic
    }
}

/// Nanoseconds since the Unix epoch (0 for a clock before it).
fn now_ns() -> i64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX))
}

/// A ROS 2 name made of `name`: `-` becomes `_` (fleet names allow it, ROS names do not).
pub fn name_token(name: &str) -> String {
    name.replace('-', "_")
}

/// The ROS 2 options of the network commands.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct Ros2Args {
    /// Also publish on ROS 2 topics over rmw_zenoh, on this process's zenoh session: ROS 2 nodes
    /// using rmw_zenoh (rviz2, `ros2 topic echo`) that reach it see them with no bridge.
    #[arg(long)]
    pub ros2: bool,
    /// The ROS domain id of those topics and of `ros2:` sources.
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub ros2_domain: u32,
}

impl Ros2Args {
    /// The domain to publish in, when publishing is asked for.
    pub fn publish_domain(&self) -> Option<u32> {
        self.ros2.then_some(self.ros2_domain)
    }
}
