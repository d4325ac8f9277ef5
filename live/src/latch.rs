//! Latched topics: the newest message of each state topic, sent to each client as it subscribes.
//! The Foxglove WebSocket protocol keeps no history, so without this a viewer opened after the
//! last merge would show no map until the next one.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{ChannelId, RawChannel};

use crate::lock;

/// A channel's newest message.
type Newest = (Arc<RawChannel>, Vec<u8>);

/// The newest message per latched channel.
#[derive(Default)]
pub(crate) struct Latch {
    enabled: AtomicBool,
    newest: Mutex<HashMap<ChannelId, Newest>>,
}

impl Latch {
    /// From now on messages are kept (a server runs).
    pub(crate) fn enable(&self) {
        self.enabled.store(true, Ordering::Release);
    }

    pub(crate) fn enabled(&self) -> bool {
        self.enabled.load(Ordering::Acquire)
    }

    /// Keeps `bytes` as the newest message of `channel`.
    pub(crate) fn keep(&self, channel: &Arc<RawChannel>, bytes: Vec<u8>) {
        lock(&self.newest).insert(channel.id(), (Arc::clone(channel), bytes));
    }
}

impl ServerListener for Latch {
    /// The SDK subscribes the client's sink before this call, so the message reaches it.
    fn on_subscribe(&self, client: Client, channel: ChannelView) {
        let newest = lock(&self.newest).get(&channel.id()).map(|(c, b)| (Arc::clone(c), b.clone()));
        if let (Some((channel, bytes)), Some(sink)) = (newest, client.sink_id()) {
            channel.log_to_sink(&bytes, Some(sink));
        }
    }
}
