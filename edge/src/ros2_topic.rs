//! A ROS 2 LiDAR driver's sensor_msgs/PointCloud2 topic over rmw_zenoh (`ros2:/TOPIC`), read with
//! no bridge on a zenoh session of its own.
//!
//! As with a live sensor, the samples arrive on zenoh's threads, which never wait on the odometry:
//! they hand each message on through a short queue, and when the queue is full the scan is dropped
//! whole and counted. The subscription is announced with rmw_zenoh's liveliness token, so the
//! driver's side sees a subscriber (`ros2 topic info`).

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, TrySendError, sync_channel};
use std::time::Duration;

use bus::Network;
use bus::ros2::Ros2Node;
use proto::ros2::POINT_CLOUD2;
use proto::ros2::keys::{Qos, TopicName, topic_key_any_type};
use tokio::sync::oneshot;
use zenoh::sample::Sample;

/// Messages received and not yet taken: enough to ride out one slow scan of the odometry.
const QUEUE: usize = 2;

/// A message as the subscription hands it on.
#[derive(Debug)]
pub struct Ros2Message {
    /// The CDR payload.
    pub payload: Vec<u8>,
    /// Scans dropped since the previous one handed on, because it was not taken in time.
    pub dropped_before: usize,
}

/// What the subscription has counted so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Ros2Counts {
    /// PointCloud2 messages received.
    pub received: usize,
    /// Scans dropped because the queue was full.
    pub dropped: usize,
    /// Samples on the topic whose type is not sensor_msgs/PointCloud2 (ignored).
    pub other_type: usize,
}

#[derive(Default)]
struct Counters {
    received: AtomicUsize,
    dropped: AtomicUsize,
    dropped_since: AtomicUsize,
    other_type: AtomicUsize,
}

/// Why a ROS 2 topic could not be subscribed to.
#[derive(Debug, thiserror::Error)]
#[error("ros2:{topic}: {reason}")]
pub struct Ros2TopicError {
    /// The topic.
    pub topic: String,
    /// Why.
    pub reason: String,
}

/// The zenoh session a subscription uses.
#[derive(Clone, Debug)]
pub enum Link {
    /// A session of its own, opened on this network (`emr-edge odometry`, `convert`).
    Join(Network),
    /// A session already open (a robot's node reads its driver on the session it publishes on).
    Session(zenoh::Session),
}

/// A subscription to a PointCloud2 topic; messages are taken with [`Ros2Topic::next_message`].
pub struct Ros2Topic {
    topic: TopicName,
    messages: Receiver<Ros2Message>,
    counters: Arc<Counters>,
    stop: Option<oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for Ros2Topic {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros2Topic").field("topic", &self.topic).finish_non_exhaustive()
    }
}

impl Ros2Topic {
    /// Subscribes to `topic` in ROS domain `domain` on `link`'s session, whatever type the key
    /// names (a sample of another type is counted and warned about once, not decoded).
    pub fn start(link: Link, domain: u32, topic: &TopicName) -> Result<Ros2Topic, Ros2TopicError> {
        let fail = |reason: String| Ros2TopicError { topic: topic.to_string(), reason };
        let (sender, messages) = sync_channel(QUEUE);
        let counters = Arc::new(Counters::default());
        let (stop, stopped) = oneshot::channel();
        let (ready, declared) = std::sync::mpsc::channel();
        let (topic_name, in_thread) = (topic.clone(), counters.clone());
        let thread = std::thread::Builder::new()
            .name("ros2-topic".into())
            .spawn(move || {
                let runtime = match tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build() {
                    Ok(r) => r,
                    Err(e) => return drop(ready.send(Err(format!("cannot start tokio: {e}")))),
                };
                runtime.block_on(async move {
                    let (session, own) = match link {
                        Link::Join(network) => match network.open().await {
                            Ok(s) => (s, true),
                            Err(e) => return drop(ready.send(Err(e.to_string()))),
                        },
                        Link::Session(s) => (s, false),
                    };
                    let key = topic_key_any_type(domain, &topic_name);
                    let counters = in_thread;
                    let subscriber = session
                        .declare_subscriber(key.clone())
                        .callback(move |sample| hand_on(&sample, &sender, &counters))
                        .await;
                    let subscriber = match subscriber {
                        Ok(s) => s,
                        Err(e) => return drop(ready.send(Err(format!("cannot subscribe to {key}: {e}")))),
                    };
                    // Announced once the subscriber is declared: a publisher that waits for the token
                    // then knows of the subscriber too (a session's declarations arrive in order).
                    let announced = async {
                        let node = Ros2Node::new(&session, domain, "/", "emr_edge_source").await?;
                        let token = node.announce_subscription(&topic_name, POINT_CLOUD2, Qos::SENSOR_DATA).await?;
                        Ok::<_, bus::ros2::Ros2Error>((node, token))
                    };
                    match announced.await {
                        Ok(entities) => {
                            let _ = ready.send(Ok(()));
                            let _ = stopped.await;
                            drop(entities);
                        }
                        Err(e) => drop(ready.send(Err(e.to_string()))),
                    }
                    drop(subscriber);
                    if own {
                        let _ = session.close().await;
                    }
                });
            })
            .map_err(|e| fail(e.to_string()))?;
        match declared.recv() {
            Ok(Ok(())) => {}
            Ok(Err(reason)) => return Err(fail(reason)),
            Err(_) => return Err(fail("the subscribing thread ended".into())),
        }
        Ok(Ros2Topic { topic: topic.clone(), messages, counters, stop: Some(stop), thread: Some(thread) })
    }

    /// The topic.
    pub fn topic(&self) -> &TopicName {
        &self.topic
    }

    /// The next message, waiting up to `timeout`; `Err(Timeout)` when none came.
    pub fn next_message(&self, timeout: Duration) -> Result<Ros2Message, RecvTimeoutError> {
        self.messages.recv_timeout(timeout)
    }

    /// What the subscription counted so far.
    pub fn counts(&self) -> Ros2Counts {
        let c = &self.counters;
        Ros2Counts {
            received: c.received.load(Ordering::Relaxed),
            dropped: c.dropped.load(Ordering::Relaxed),
            other_type: c.other_type.load(Ordering::Relaxed),
        }
    }
}

impl Drop for Ros2Topic {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// On zenoh's thread: a PointCloud2 sample into the queue, or dropped and counted when it is full.
fn hand_on(sample: &Sample, sender: &std::sync::mpsc::SyncSender<Ros2Message>, counters: &Counters) {
    // DOMAIN/TOPIC.../DDS_TYPE/HASH: the type is the next-to-last chunk.
    let key = sample.key_expr().as_str();
    let dds = key.rsplit('/').nth(1).unwrap_or_default();
    if dds != POINT_CLOUD2.dds {
        if counters.other_type.fetch_add(1, Ordering::Relaxed) == 0 {
            tracing::warn!("{key}: not a {} topic; its samples are ignored", POINT_CLOUD2.name);
        }
        return;
    }
    counters.received.fetch_add(1, Ordering::Relaxed);
    let message = Ros2Message {
        payload: sample.payload().to_bytes().into_owned(),
        dropped_before: counters.dropped_since.load(Ordering::Relaxed),
    };
    let dropped_before = message.dropped_before;
    match sender.try_send(message) {
        Ok(()) => drop(counters.dropped_since.fetch_sub(dropped_before, Ordering::Relaxed)),
        Err(TrySendError::Full(_)) => {
            counters.dropped.fetch_add(1, Ordering::Relaxed);
            counters.dropped_since.fetch_add(1, Ordering::Relaxed);
        }
        Err(TrySendError::Disconnected(_)) => {}
    }
}
