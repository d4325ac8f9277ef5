//! The robot's keyframes on disk (`emr-edge run --state DIR`, the systemd unit's StateDirectory), so
//! that after a crash or a reboot the station can still backfill what it missed of every session.
//!
//! Layout: `DIR/keyframes/SESSION/SEQ.pb`, each the `Keyframe` message exactly as published, written
//! to a temporary name and renamed, so a crash leaves no half-written keyframe under a real name.
//! A directory that does not read back (a name that is no session or sequence number, a message
//! that does not decode or names another robot, session or sequence number) is set aside as
//! `DIR/damaged-N` with a warning and the robot starts with an empty one: a robot must map even
//! when its disk is in trouble. A state directory that cannot be written at all is given up with a
//! warning, for the same reason.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use prost::Message;
use proto::{Keyframe, KeyframeRequest};
use tracing::warn;

const KEYFRAMES: &str = "keyframes";
const SUFFIX: &str = "pb";

/// Keyframes on disk, by session and sequence number.
#[derive(Debug)]
pub struct StateDir {
    root: PathBuf,
    robot: u32,
    /// Sequence numbers held per session.
    held: BTreeMap<u64, Vec<u64>>,
}

/// Why a state directory was not read back as it is.
#[derive(Debug, thiserror::Error)]
pub enum StateError {
    /// A file or directory could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// What was being read or written.
        path: PathBuf,
        /// What the system said.
        source: std::io::Error,
    },
    /// What is there is not what this robot wrote.
    #[error("{path}: {reason}")]
    Damaged {
        /// The file or directory.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
}

impl StateDir {
    /// Opens `root` for `robot`, reading back what earlier sessions left; a damaged directory is
    /// set aside with a warning. `None` (with a warning) when `root` cannot be used at all.
    pub fn open(root: &Path, robot: u32) -> Option<StateDir> {
        match Self::read(root, robot) {
            Ok(dir) => return Some(dir),
            Err(e) => warn!("robot {robot}: state directory {}: {e}", root.display()),
        }
        let aside = set_aside(root)?;
        warn!("robot {robot}: damaged keyframes set aside as {}; starting without them", aside.display());
        match Self::read(root, robot) {
            Ok(dir) => Some(dir),
            Err(e) => {
                warn!(
                    "robot {robot}: state directory {} unusable ({e}): keyframes are kept in memory only",
                    root.display()
                );
                None
            }
        }
    }

    fn read(root: &Path, robot: u32) -> Result<StateDir, StateError> {
        let dir = root.join(KEYFRAMES);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        let mut held = BTreeMap::new();
        for entry in std::fs::read_dir(&dir).map_err(io(&dir))? {
            let path = entry.map_err(io(&dir))?.path();
            let session = number(&path, None)?;
            held.insert(session, read_session(&path, robot, session)?);
        }
        Ok(StateDir { root: root.to_owned(), robot, held })
    }

    /// The newest session held, if any.
    pub fn newest_session(&self) -> Option<u64> {
        self.held.keys().next_back().copied()
    }

    /// Keyframes held over all sessions.
    pub fn keyframes(&self) -> usize {
        self.held.values().map(Vec::len).sum()
    }

    /// Writes keyframe `seq` of `session` (its message bytes as published).
    pub fn write(&mut self, session: u64, seq: u64, payload: &[u8]) -> Result<(), StateError> {
        let dir = self.session_dir(session);
        std::fs::create_dir_all(&dir).map_err(io(&dir))?;
        let path = dir.join(format!("{seq}.{SUFFIX}"));
        let temporary = dir.join(format!(".{seq}.{SUFFIX}.new"));
        std::fs::write(&temporary, payload).map_err(io(&temporary))?;
        std::fs::rename(&temporary, &path).map_err(io(&path))?;
        let seqs = self.held.entry(session).or_default();
        if let Err(at) = seqs.binary_search(&seq) {
            seqs.insert(at, seq);
        }
        Ok(())
    }

    /// The keyframes of `session` a request asks for, in sequence order, the first `limit` of them;
    /// a file that can no longer be read is left out with a warning.
    pub fn select(&self, session: u64, request: &KeyframeRequest) -> Vec<(u64, Vec<u8>)> {
        let Some(seqs) = self.held.get(&session) else { return Vec::new() };
        let wanted = |s: &&u64| request.seqs.contains(s) || request.from_seq.is_some_and(|from| **s >= from);
        let limit = request.limit.map_or(usize::MAX, |l| l as usize);
        let dir = self.session_dir(session);
        seqs.iter()
            .filter(wanted)
            .filter_map(|&seq| {
                let path = dir.join(format!("{seq}.{SUFFIX}"));
                match std::fs::read(&path) {
                    Ok(bytes) => Some((seq, bytes)),
                    Err(e) => {
                        warn!("robot {}: cannot read {}: {e}", self.robot, path.display());
                        None
                    }
                }
            })
            .take(limit)
            .collect()
    }

    fn session_dir(&self, session: u64) -> PathBuf {
        self.root.join(KEYFRAMES).join(session.to_string())
    }
}

/// The sequence numbers of one session's directory, each file checked to be that keyframe.
fn read_session(dir: &Path, robot: u32, session: u64) -> Result<Vec<u64>, StateError> {
    let mut seqs = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(io(dir))? {
        let path = entry.map_err(io(dir))?.path();
        if path.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with('.')) {
            // A write a crash interrupted: never renamed, never published from disk.
            continue;
        }
        let seq = number(&path, Some(SUFFIX))?;
        let bytes = std::fs::read(&path).map_err(io(&path))?;
        let kf = Keyframe::decode(bytes.as_slice()).map_err(|e| damaged(&path, format!("not a Keyframe: {e}")))?;
        if (kf.robot, kf.session, kf.seq) != (robot, session, seq) {
            let found = format!("robot {} session {} keyframe {}", kf.robot, kf.session, kf.seq);
            return Err(damaged(&path, format!("holds {found}, not robot {robot} session {session} keyframe {seq}")));
        }
        seqs.push(seq);
    }
    seqs.sort_unstable();
    Ok(seqs)
}

/// The number a path is named (with `suffix`, when given).
fn number(path: &Path, suffix: Option<&str>) -> Result<u64, StateError> {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
    let stem = match suffix {
        Some(suffix) => name.strip_suffix(suffix).and_then(|s| s.strip_suffix('.')),
        None => Some(name),
    };
    stem.and_then(|s| s.parse().ok()).ok_or_else(|| damaged(path, "not a name this robot writes".into()))
}

/// Moves `root/keyframes` to the first free `root/damaged-N`; `None` (with a warning) when it
/// cannot be moved.
fn set_aside(root: &Path) -> Option<PathBuf> {
    let from = root.join(KEYFRAMES);
    let to = (0..).map(|n| root.join(format!("damaged-{n}"))).find(|p| !p.exists())?;
    match std::fs::rename(&from, &to) {
        Ok(()) => Some(to),
        Err(e) => {
            warn!("cannot set {} aside as {}: {e}; keyframes are kept in memory only", from.display(), to.display());
            None
        }
    }
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> StateError {
    let path = path.to_owned();
    move |source| StateError::Io { path: path.clone(), source }
}

fn damaged(path: &Path, reason: String) -> StateError {
    StateError::Damaged { path: path.to_owned(), reason }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn keyframe(robot: u32, session: u64, seq: u64) -> Vec<u8> {
        Keyframe { fleet: "f".into(), robot, session, seq, ..Default::default() }.encode_to_vec()
    }

    fn seqs(selected: Vec<(u64, Vec<u8>)>) -> Vec<u64> {
        selected.into_iter().map(|(s, _)| s).collect()
    }

    #[test]
    fn keyframes_of_every_session_are_read_back_after_a_restart() {
        let root = tempfile::tempdir().unwrap();
        let mut dir = StateDir::open(root.path(), 3).unwrap();
        assert_eq!(dir.newest_session(), None);
        for seq in 0..5 {
            dir.write(10, seq, &keyframe(3, 10, seq)).unwrap();
        }
        dir.write(11, 0, &keyframe(3, 11, 0)).unwrap();
        // A crash in the middle of a write leaves a temporary file, never a keyframe.
        std::fs::write(root.path().join("keyframes/11/.1.pb.new"), b"half").unwrap();
        drop(dir);
        let dir = StateDir::open(root.path(), 3).unwrap();
        assert_eq!((dir.newest_session(), dir.keyframes()), (Some(11), 6));
        let request = KeyframeRequest { seqs: vec![1], from_seq: Some(3), limit: Some(2), session: Some(10) };
        let selected = dir.select(10, &request);
        assert_eq!(selected[0].1, keyframe(3, 10, 1), "the bytes as published");
        assert_eq!(seqs(selected), vec![1, 3]);
        assert_eq!(seqs(dir.select(12, &request)), Vec::<u64>::new());
    }

    #[test]
    fn a_damaged_directory_is_set_aside_and_the_robot_starts_empty() {
        for damage in ["garbage", "other robot", "wrong name"] {
            let root = tempfile::tempdir().unwrap();
            let mut dir = StateDir::open(root.path(), 3).unwrap();
            dir.write(10, 0, &keyframe(3, 10, 0)).unwrap();
            let session = root.path().join("keyframes/10");
            match damage {
                "garbage" => std::fs::write(session.join("1.pb"), [0xff; 9]).unwrap(),
                "other robot" => std::fs::write(session.join("1.pb"), keyframe(4, 10, 1)).unwrap(),
                _ => std::fs::write(session.join("one.pb"), keyframe(3, 10, 1)).unwrap(),
            }
            let dir = StateDir::open(root.path(), 3).unwrap_or_else(|| panic!("{damage}: gave up the directory"));
            assert_eq!((dir.newest_session(), dir.keyframes()), (None, 0), "{damage}");
            assert!(root.path().join("damaged-0/10/0.pb").exists(), "{damage}: not set aside");
        }
    }
}
