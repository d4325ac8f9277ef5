//! The node's queryables: the keyframe store answers `KeyframeRequest`s with the keyframes still
//! held; the pose-graph key answers with the newest update.

use std::sync::{Arc, Mutex, PoisonError};

use prost::Message;
use proto::KeyframeRequest;
use tokio::sync::oneshot;
use tracing::{debug, warn};
use zenoh::bytes::ZBytes;
use zenoh::handlers::FifoChannelHandler;
use zenoh::query::{Query, Queryable};

use super::store::Store;

/// Serves queries until `stop` fires (or is dropped), then undeclares the queryable.
pub(crate) async fn serve(
    queryable: Queryable<FifoChannelHandler<Query>>,
    store: Arc<Mutex<Store>>,
    mut stop: oneshot::Receiver<()>,
) {
    loop {
        tokio::select! {
            _ = &mut stop => break,
            query = queryable.recv_async() => match query {
                Ok(query) => answer(&query, &store).await,
                Err(_) => break,
            },
        }
    }
    if let Err(e) = queryable.undeclare().await {
        warn!("cannot undeclare the keyframe queryable: {e}");
    }
}

/// One `Keyframe` reply per held keyframe asked for; an error reply to a request that does not decode.
async fn answer(query: &Query, store: &Mutex<Store>) {
    let key = query.key_expr().clone();
    let request = match decode(query) {
        Ok(r) => r,
        Err(e) => {
            warn!("malformed KeyframeRequest on {key}: {e}");
            if let Err(e) = query.reply_err(format!("malformed KeyframeRequest: {e}")).await {
                warn!("cannot reply to a query on {key}: {e}");
            }
            return;
        }
    };
    // A panic elsewhere cannot leave the store half-updated: insert and evict keep it consistent.
    let held = store.lock().unwrap_or_else(PoisonError::into_inner).select(&request);
    debug!("{key}: {} of the requested keyframes held", held.len());
    for (seq, payload) in held {
        if let Err(e) = query.reply(key.clone(), payload).await {
            warn!("cannot reply keyframe {seq} on {key}: {e}");
            return;
        }
    }
}

/// Serves queries on the pose-graph key with the newest update (none yet: no reply) until `stop`.
pub(crate) async fn serve_latest(
    queryable: Queryable<FifoChannelHandler<Query>>,
    latest: Arc<Mutex<Option<ZBytes>>>,
    mut stop: oneshot::Receiver<()>,
) {
    loop {
        tokio::select! {
            _ = &mut stop => break,
            query = queryable.recv_async() => match query {
                Ok(query) => {
                    let held = latest.lock().unwrap_or_else(PoisonError::into_inner).clone();
                    if let Some(payload) = held
                        && let Err(e) = query.reply(query.key_expr().clone(), payload).await
                    {
                        warn!("cannot reply the pose graph on {}: {e}", query.key_expr());
                    }
                }
                Err(_) => break,
            },
        }
    }
    if let Err(e) = queryable.undeclare().await {
        warn!("cannot undeclare the pose-graph queryable: {e}");
    }
}

/// The request in a query; no payload is the empty request.
fn decode(query: &Query) -> Result<KeyframeRequest, prost::DecodeError> {
    match query.payload() {
        Some(payload) => KeyframeRequest::decode(payload.to_bytes().as_ref()),
        None => Ok(KeyframeRequest::default()),
    }
}
