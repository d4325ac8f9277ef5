//! Rounds of estimation ([`Round`]) on threads of their own, beside the merge jobs.
//!
//! A merge job composes and publishes the global map from the placements found so far, in a
//! fraction of a second; the round that finds new placements (preparing grown maps, tracking and
//! searching pairs) takes seconds at 16 robots and runs here meanwhile. When it is done the
//! estimator calls back, and the next merge job applies it. Its threads run at a lower priority
//! (nice 10): on a small station the cores are shared, and the publishing path must not wait
//! behind a round.

use std::panic::AssertUnwindSafe;
use std::sync::{Arc, Mutex, PoisonError};

use crate::merge::Round;

/// What the estimator calls when a round has finished (from the round's thread).
pub type Notify = Arc<dyn Fn() + Send + Sync>;

/// Niceness of the estimation threads: below the merge jobs and the network.
const NICE: i32 = 10;

/// Where a round's thread leaves it: `Err` with the panic's message when it failed.
type Outcome = Arc<Mutex<Option<Result<Round, String>>>>;

/// Runs at most one round at a time.
pub struct Estimator {
    pool: rayon::ThreadPool,
    running: Option<Outcome>,
    notify: Notify,
}

impl Estimator {
    /// An idle estimator with a thread per core; `notify` is called when a round finishes.
    pub fn new(notify: Notify) -> Result<Self, rayon::ThreadPoolBuildError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .thread_name(|i| format!("estimate-{i}"))
            .start_handler(|_| lower_priority())
            .build()?;
        Ok(Self { pool, running: None, notify })
    }

    /// True while a round runs (or has finished and not been taken).
    pub fn busy(&self) -> bool {
        self.running.is_some()
    }

    /// Starts `round`. Only one at a time: the caller takes the last one ([`Estimator::finished`]) first.
    pub fn start(&mut self, mut round: Round) {
        debug_assert!(self.running.is_none(), "one round at a time");
        let outcome = Outcome::default();
        let (left, notify) = (Arc::clone(&outcome), Arc::clone(&self.notify));
        self.pool.spawn(move || {
            let ran = std::panic::catch_unwind(AssertUnwindSafe(|| {
                round.run();
                round
            }));
            *left.lock().unwrap_or_else(PoisonError::into_inner) = Some(ran.map_err(|p| panic_message(p.as_ref())));
            notify();
        });
        self.running = Some(outcome);
    }

    /// The round that has finished, if one has: `Err` with the panic's message when it failed.
    pub fn finished(&mut self) -> Option<Result<Round, String>> {
        let done = self.running.as_ref()?.lock().unwrap_or_else(PoisonError::into_inner).take()?;
        self.running = None;
        Some(done)
    }
}

fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    let text = panic.downcast_ref::<&str>().copied().or_else(|| panic.downcast_ref::<String>().map(String::as_str));
    format!("the round panicked: {}", text.unwrap_or("(no message)"))
}

/// Lowers the calling thread's scheduling priority (Linux: a thread's nice value is its own).
fn lower_priority() {
    #[cfg(target_os = "linux")]
    // SAFETY: gettid has no preconditions; setpriority on the caller's own thread id only changes
    // that thread's nice value, and a failure (not permitted) leaves it as it was.
    unsafe {
        let tid = libc::gettid();
        libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, NICE);
    }
}
