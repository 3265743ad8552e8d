//! The journal of accepted jobs (the embedded default's durability): one file per job that was
//! accepted but has not finished, written and fsynced before the submission is acknowledged and
//! removed when the job ends. After a crash (`kill -9`, power loss) the files left are the jobs
//! to run again; a job stopped by a graceful shutdown keeps its file too, so a restart finishes
//! it. The request is kept as the opaque bytes the service layer gave, so this module knows
//! nothing of protobuf.
//!
//! File `<id>.<hex tenant>.job`: magic, then length-prefixed tenant, id, method and request,
//! then the SHA-256 of everything before it. A file that fails the check is removed with a
//! warning (its job cannot be rebuilt).

use std::io::Write;
use std::path::{Path, PathBuf};

use sha2::{Digest, Sha256};

const MAGIC: &[u8; 8] = b"MURKJOB1";
const EXTENSION: &str = "job";

/// One accepted job as the journal keeps it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct JournalEntry {
    /// Owning tenant (`""` without authentication).
    pub tenant: String,
    /// Job id (content hash).
    pub id: String,
    /// Method name.
    pub method: String,
    /// The request, as the service layer encoded it.
    pub request: Vec<u8>,
}

/// A directory of journal files.
#[derive(Debug)]
pub struct Journal {
    dir: PathBuf,
}

impl Journal {
    /// Opens (creating) the journal directory.
    pub fn open(dir: &Path) -> std::io::Result<Self> {
        std::fs::create_dir_all(dir)?;
        Ok(Self {
            dir: dir.to_path_buf(),
        })
    }

    fn path(&self, tenant: &str, id: &str) -> PathBuf {
        self.dir
            .join(format!("{id}.{}.{EXTENSION}", hex::encode(tenant)))
    }

    /// Writes `entry` durably (temporary file, fsync, rename, directory fsync).
    pub fn record(&self, entry: &JournalEntry) -> std::io::Result<()> {
        let path = self.path(&entry.tenant, &entry.id);
        let tmp = path.with_extension(format!("tmp{}", std::process::id()));
        let body = encode(entry);
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(&body)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, &path)?;
        std::fs::File::open(&self.dir)?.sync_all()
    }

    /// True when the job has a journal file.
    pub fn contains(&self, tenant: &str, id: &str) -> bool {
        self.path(tenant, id).exists()
    }

    /// Forgets the job (it ended). Missing files are fine.
    pub fn remove(&self, tenant: &str, id: &str) {
        let path = self.path(tenant, id);
        if let Err(e) = std::fs::remove_file(&path) {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::warn!(path = %path.display(), error = %e, "could not remove journal file");
            }
        }
    }

    /// Every intact entry, oldest first (by file time); corrupt files are removed.
    pub fn load(&self) -> Vec<JournalEntry> {
        let Ok(read) = std::fs::read_dir(&self.dir) else {
            return Vec::new();
        };
        let mut found = Vec::new();
        for e in read.filter_map(|e| e.ok()) {
            let path = e.path();
            if path.extension().is_none_or(|x| x != EXTENSION) {
                continue;
            }
            match std::fs::read(&path).ok().and_then(|b| decode(&b)) {
                Some(entry) => {
                    let t = e
                        .metadata()
                        .and_then(|m| m.modified())
                        .unwrap_or(std::time::UNIX_EPOCH);
                    found.push((t, entry));
                }
                None => {
                    tracing::warn!(path = %path.display(), "corrupt journal file removed");
                    let _ = std::fs::remove_file(&path);
                }
            }
        }
        found.sort_by_key(|(t, _)| *t);
        found.into_iter().map(|(_, e)| e).collect()
    }
}

fn encode(e: &JournalEntry) -> Vec<u8> {
    let mut b = Vec::with_capacity(e.request.len() + 128);
    b.extend_from_slice(MAGIC);
    for part in [
        e.tenant.as_bytes(),
        e.id.as_bytes(),
        e.method.as_bytes(),
        &e.request,
    ] {
        b.extend_from_slice(&(part.len() as u64).to_le_bytes());
        b.extend_from_slice(part);
    }
    let sum = Sha256::digest(&b);
    b.extend_from_slice(&sum);
    b
}

fn decode(bytes: &[u8]) -> Option<JournalEntry> {
    if bytes.len() < MAGIC.len() + 32 {
        return None;
    }
    let (body, sum) = bytes.split_at(bytes.len() - 32);
    if Sha256::digest(body).as_slice() != sum {
        return None;
    }
    let mut rest = body.strip_prefix(MAGIC.as_slice())?;
    let mut parts = Vec::with_capacity(4);
    for _ in 0..4 {
        let (len, tail) = rest.split_at_checked(8)?;
        let len = usize::try_from(u64::from_le_bytes(len.try_into().ok()?)).ok()?;
        let (part, tail) = tail.split_at_checked(len)?;
        parts.push(part);
        rest = tail;
    }
    if !rest.is_empty() {
        return None;
    }
    let text = |p: &[u8]| String::from_utf8(p.to_vec()).ok();
    Some(JournalEntry {
        tenant: text(parts[0])?,
        id: text(parts[1])?,
        method: text(parts[2])?,
        request: parts[3].to_vec(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(tenant: &str, id: &str) -> JournalEntry {
        JournalEntry {
            tenant: tenant.into(),
            id: id.into(),
            method: "tof_depth".into(),
            request: vec![1, 2, 3, 0, 255],
        }
    }

    #[test]
    fn entries_round_trip_and_corruption_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let j = Journal::open(dir.path()).unwrap();
        j.record(&entry("", "aa")).unwrap();
        j.record(&entry("fleet-a", "aa")).unwrap();
        let mut got = j.load();
        got.sort_by(|a, b| a.tenant.cmp(&b.tenant));
        assert_eq!(got, vec![entry("", "aa"), entry("fleet-a", "aa")]);
        j.remove("", "aa");
        assert_eq!(j.load(), vec![entry("fleet-a", "aa")]);
        // Flip one byte: the file fails its checksum and is removed.
        let path = j.path("fleet-a", "aa");
        let mut b = std::fs::read(&path).unwrap();
        b[12] ^= 1;
        std::fs::write(&path, b).unwrap();
        assert!(j.load().is_empty());
        assert!(!path.exists());
        assert_eq!(decode(&encode(&entry("t", "bb"))), Some(entry("t", "bb")));
        assert_eq!(decode(b"MURKJOB1"), None);
    }
}
