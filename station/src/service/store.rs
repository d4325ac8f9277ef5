//! Persistence in an embedded redb database (`DIR/station.redb`): every keyframe as received, each
//! robot session's latest pose-graph update, the latest global map and what it was built from.
//!
//! Rows are keyed by robot session. A database written before sessions (tables keyed by robot) is
//! read as session 0 of each robot; new rows go to the session tables.
//!
//! Writes go through a writer thread that commits in batches (every [`BATCH_PERIOD`] or
//! [`BATCH_ITEMS`] writes), so a `kill -9` loses at most the last batch, which the backfill from the
//! robots then recovers.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use redb::{Database, DatabaseError, ReadableDatabase, ReadableTable, TableDefinition};

use super::fleet_state::{Basis, Member};

/// The database file's name inside the data directory.
pub const FILE_NAME: &str = "station.redb";

/// Longest a received item waits before its batch is committed.
pub const BATCH_PERIOD: Duration = Duration::from_millis(100);

/// Writes that make a batch commit at once.
pub const BATCH_ITEMS: usize = 256;

/// How long to wait for a previous station in this process (stopped but not yet closed) to release
/// the file before calling it taken.
const OPEN_PATIENCE: Duration = Duration::from_secs(5);

/// (robot, session, seq): Keyframe bytes.
const KEYFRAMES: TableDefinition<(u32, u64, u64), &[u8]> = TableDefinition::new("session_keyframes");
/// (robot, session): PoseGraphUpdate bytes.
const POSEGRAPHS: TableDefinition<(u32, u64), &[u8]> = TableDefinition::new("session_posegraphs");
const GLOBAL_MAP: TableDefinition<&str, &[u8]> = TableDefinition::new("global_map");
/// Per robot session: (keyframes, pose revision + 1 or 0) the persisted global map was built from.
const MAP_BASIS: TableDefinition<(u32, u64), (u64, u64)> = TableDefinition::new("session_map_basis");
/// The tables before sessions, keyed by robot: read as session 0.
const LEGACY_KEYFRAMES: TableDefinition<(u32, u64), &[u8]> = TableDefinition::new("keyframes");
const LEGACY_POSEGRAPHS: TableDefinition<u32, &[u8]> = TableDefinition::new("posegraphs");
const LEGACY_MAP_BASIS: TableDefinition<u32, (u64, u64)> = TableDefinition::new("map_basis");
const LATEST: &str = "latest";

/// The database could not be opened, read or written.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The data directory could not be created.
    #[error("cannot create data directory {path}: {source}")]
    Dir {
        /// The directory.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// Another station holds the file.
    #[error("{path} is in use by another station")]
    InUse {
        /// The database file.
        path: PathBuf,
    },
    /// redb failed.
    #[error("station database {path}: {source}")]
    Db {
        /// The database file.
        path: PathBuf,
        /// What redb said.
        source: Box<redb::Error>,
    },
}

/// One write for the writer thread.
#[derive(Clone, Debug)]
pub enum Write {
    /// A keyframe as received.
    Keyframe {
        /// Robot session.
        member: Member,
        /// Sequence number.
        seq: u64,
        /// The protobuf bytes.
        bytes: Arc<[u8]>,
    },
    /// A robot session's latest pose-graph update as received.
    PoseGraph {
        /// Robot session.
        member: Member,
        /// The protobuf bytes.
        bytes: Arc<[u8]>,
    },
    /// A published global map and what it was built from.
    GlobalMap {
        /// Its revision.
        revision: u64,
        /// The protobuf bytes as published.
        bytes: Arc<[u8]>,
        /// Per robot session, the basis of its map.
        basis: BTreeMap<Member, Basis>,
    },
}

/// Everything the database holds.
#[derive(Clone, Debug, Default)]
pub struct Persisted {
    /// (robot session, seq, Keyframe bytes), in key order.
    pub keyframes: Vec<(Member, u64, Vec<u8>)>,
    /// (robot session, PoseGraphUpdate bytes).
    pub posegraphs: Vec<(Member, Vec<u8>)>,
    /// The latest GlobalMap bytes.
    pub global_map: Option<Vec<u8>>,
    /// What that map was built from.
    pub basis: BTreeMap<Member, Basis>,
}

/// The open database.
pub struct Store {
    db: Database,
    path: PathBuf,
}

impl Store {
    /// Opens (or creates) `dir/station.redb`, creating `dir` if needed.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        std::fs::create_dir_all(dir).map_err(|source| StoreError::Dir { path: dir.to_owned(), source })?;
        let path = dir.join(FILE_NAME);
        let db = open_patiently(&path)?;
        let store = Store { db, path };
        store.create_tables()?;
        Ok(store)
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn create_tables(&self) -> Result<(), StoreError> {
        self.write(|txn| {
            txn.open_table(KEYFRAMES)?;
            txn.open_table(POSEGRAPHS)?;
            txn.open_table(GLOBAL_MAP)?;
            txn.open_table(MAP_BASIS)?;
            txn.open_table(LEGACY_KEYFRAMES)?;
            txn.open_table(LEGACY_POSEGRAPHS)?;
            txn.open_table(LEGACY_MAP_BASIS)?;
            Ok(())
        })
    }

    /// Reads everything back.
    pub fn load(&self) -> Result<Persisted, StoreError> {
        self.read().map_err(|e| self.error(e))
    }

    fn read(&self) -> Result<Persisted, redb::Error> {
        let txn = self.db.begin_read()?;
        let mut out = Persisted::default();
        for row in txn.open_table(LEGACY_KEYFRAMES)?.iter()? {
            let (k, v) = row?;
            let (robot, seq) = k.value();
            out.keyframes.push((Member::from(robot), seq, v.value().to_vec()));
        }
        for row in txn.open_table(KEYFRAMES)?.iter()? {
            let (k, v) = row?;
            let (robot, session, seq) = k.value();
            out.keyframes.push((Member::new(robot, session), seq, v.value().to_vec()));
        }
        for row in txn.open_table(LEGACY_POSEGRAPHS)?.iter()? {
            let (k, v) = row?;
            out.posegraphs.push((Member::from(k.value()), v.value().to_vec()));
        }
        for row in txn.open_table(POSEGRAPHS)?.iter()? {
            let (k, v) = row?;
            let (robot, session) = k.value();
            out.posegraphs.push((Member::new(robot, session), v.value().to_vec()));
        }
        out.global_map = txn.open_table(GLOBAL_MAP)?.get(LATEST)?.map(|v| v.value().to_vec());
        let basis = |(keyframes, pose): (u64, u64)| Basis { keyframes, pose_revision: pose.checked_sub(1) };
        for row in txn.open_table(LEGACY_MAP_BASIS)?.iter()? {
            let (k, v) = row?;
            out.basis.insert(Member::from(k.value()), basis(v.value()));
        }
        for row in txn.open_table(MAP_BASIS)?.iter()? {
            let (k, v) = row?;
            let (robot, session) = k.value();
            out.basis.insert(Member::new(robot, session), basis(v.value()));
        }
        Ok(out)
    }

    /// Commits `batch` in one transaction.
    pub fn commit(&self, batch: &[Write]) -> Result<(), StoreError> {
        self.write(|txn| {
            let mut keyframes = txn.open_table(KEYFRAMES)?;
            let mut posegraphs = txn.open_table(POSEGRAPHS)?;
            let mut global_map = txn.open_table(GLOBAL_MAP)?;
            let mut map_basis = txn.open_table(MAP_BASIS)?;
            let mut legacy_basis = txn.open_table(LEGACY_MAP_BASIS)?;
            for w in batch {
                match w {
                    Write::Keyframe { member, seq, bytes } => {
                        keyframes.insert((member.robot, member.session, *seq), bytes.as_ref())?;
                    }
                    Write::PoseGraph { member, bytes } => {
                        posegraphs.insert((member.robot, member.session), bytes.as_ref())?;
                    }
                    Write::GlobalMap { bytes, basis, .. } => {
                        global_map.insert(LATEST, bytes.as_ref())?;
                        map_basis.retain(|_, _| false)?;
                        legacy_basis.retain(|_, _| false)?;
                        for (m, b) in basis {
                            let pose = b.pose_revision.map_or(0, |r| r + 1);
                            map_basis.insert((m.robot, m.session), (b.keyframes, pose))?;
                        }
                    }
                }
            }
            Ok(())
        })
    }

    fn write(&self, f: impl FnOnce(&redb::WriteTransaction) -> Result<(), redb::Error>) -> Result<(), StoreError> {
        let run = || -> Result<(), redb::Error> {
            let txn = self.db.begin_write()?;
            f(&txn)?;
            txn.commit()?;
            Ok(())
        };
        run().map_err(|e| self.error(e))
    }

    fn error(&self, source: redb::Error) -> StoreError {
        StoreError::Db { path: self.path.clone(), source: Box::new(source) }
    }
}

/// Opens the file, waiting a little while it is still held: a station stopped in this process
/// releases it only when its writer thread has committed its last batch.
fn open_patiently(path: &Path) -> Result<Database, StoreError> {
    let start = Instant::now();
    loop {
        match Database::create(path) {
            Ok(db) => return Ok(db),
            Err(DatabaseError::DatabaseAlreadyOpen) if start.elapsed() < OPEN_PATIENCE => {
                std::thread::sleep(Duration::from_millis(50))
            }
            Err(DatabaseError::DatabaseAlreadyOpen) => return Err(StoreError::InUse { path: path.to_owned() }),
            Err(e) => return Err(StoreError::Db { path: path.to_owned(), source: Box::new(e.into()) }),
        }
    }
}

/// What the writer thread has committed so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Committed {
    /// Keyframes committed.
    pub keyframes: u64,
    /// Revision of the last global map committed.
    pub map_revision: u64,
    /// Batches that failed to commit (logged).
    pub failures: u64,
}

impl Committed {
    fn add(&mut self, batch: &[Write]) {
        for w in batch {
            match w {
                Write::Keyframe { .. } => self.keyframes += 1,
                Write::GlobalMap { revision, .. } => self.map_revision = self.map_revision.max(*revision),
                Write::PoseGraph { .. } => {}
            }
        }
    }
}

/// Starts the writer thread; it commits until every sender is dropped, then commits what is left
/// and exits. `on_commit` hears about each commit.
pub fn spawn_writer(store: Store, on_commit: impl Fn(Committed) + Send + 'static) -> (Sender<Write>, JoinHandle<()>) {
    let (tx, rx) = std::sync::mpsc::channel();
    let handle = std::thread::Builder::new()
        .name("station-db".into())
        .spawn(move || write_batches(&store, &rx, on_commit))
        .expect("spawning a thread only fails when the system is out of resources");
    (tx, handle)
}

/// The writer loop.
fn write_batches(store: &Store, rx: &Receiver<Write>, on_commit: impl Fn(Committed)) {
    let mut committed = Committed::default();
    while let Ok(first) = rx.recv() {
        let (batch, open) = gather(rx, first);
        match store.commit(&batch) {
            Ok(()) => committed.add(&batch),
            Err(e) => {
                // The data is still in memory and on the robots: keep serving, try the next batch.
                committed.failures += 1;
                tracing::error!("{e}");
            }
        }
        on_commit(committed);
        if !open {
            break;
        }
    }
}

/// A batch starting with `first`: what arrives within [`BATCH_PERIOD`], up to [`BATCH_ITEMS`].
/// The flag is false when the channel has closed.
fn gather(rx: &Receiver<Write>, first: Write) -> (Vec<Write>, bool) {
    let deadline = Instant::now() + BATCH_PERIOD;
    let mut batch = vec![first];
    while batch.len() < BATCH_ITEMS {
        match rx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            Ok(w) => batch.push(w),
            Err(RecvTimeoutError::Timeout) => return (batch, true),
            Err(RecvTimeoutError::Disconnected) => return (batch, false),
        }
    }
    (batch, true)
}
