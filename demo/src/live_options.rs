//! `emr-demo`'s live view and recording options: served and recorded by default.

use std::net::SocketAddr;
use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result};
use clap::Args;
use live::{Live, Sinks};

/// Where the demo's live view goes.
#[derive(Args, Debug)]
pub struct LiveArgs {
    /// Serve the live view over the Foxglove WebSocket protocol on this address: open
    /// ws://ADDR in Foxglove to watch the maps merge (topics in docs/watching.md).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:8765")]
    foxglove: SocketAddr,
    /// Serve no live view.
    #[arg(long)]
    no_foxglove: bool,
    /// Record the live view's topics to this MCAP file [default: OUT/run.mcap].
    #[arg(long, value_name = "FILE.mcap")]
    record: Option<std::path::PathBuf>,
    /// Record nothing.
    #[arg(long, conflicts_with = "record")]
    no_record: bool,
}

impl LiveArgs {
    fn sinks(&self, out: &Path) -> Sinks {
        Sinks {
            foxglove: (!self.no_foxglove).then_some(self.foxglove),
            record: (!self.no_record).then(|| self.record.clone().unwrap_or_else(|| out.join("run.mcap"))),
        }
    }

    /// Starts the sinks (inside the runtime) and says where they are.
    pub async fn open(&self, out: &Path) -> Result<Option<Arc<Live>>> {
        let sinks = self.sinks(out);
        let live = Live::open(&sinks, "emr-demo")
            .await
            .context("the live view (--foxglove ADDR serves it elsewhere, --no-foxglove not at all)")?;
        if let Some(addr) = live.as_ref().and_then(|l| l.address()) {
            println!("Foxglove: ws://{addr}");
        }
        if let Some(path) = &sinks.record {
            println!("recording to {}", path.display());
        }
        Ok(live)
    }
}
