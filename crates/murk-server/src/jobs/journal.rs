//! The journal of accepted jobs (the embedded default's durability): one file per job that was
//! accepted but has not finished, written and fsynced before the submission is acknowledged and
//! removed when the job ends. After a crash (`kill -9`, power loss) the files left are the jobs
//! to run again; a job stopped by a graceful shutdown keeps its file too, so a restart finishes
//! it. The request is kept as the opaque bytes the service layer gave, so this module knows
//! nothing of protobuf.
//!
//! File `<id>.<hex tenant>.job`: magic, then length-prefixed tenant, id, method and request,
//! then the SHA-256 of everything before it. A file that fails the check cannot be rebuilt, but
//! its name still says whose job it was: [`Journal::load`] reports it as [`Damaged`], so the
//! manager can record the job as lost before the file goes.

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

/// A journal file whose contents fail the check, named by the job it held.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Damaged {
    /// Owning tenant, from the file name.
    pub tenant: String,
    /// Job id, from the file name.
    pub id: String,
}

/// What [`Journal::load`] found.
#[derive(Debug, Default)]
pub struct Loaded {
    /// Intact entries, oldest first (by file time).
    pub entries: Vec<JournalEntry>,
    /// Files that fail the check but whose names identify the job; still on disk (remove them
    /// with [`Journal::remove`] once the loss is recorded).
    pub damaged: Vec<Damaged>,
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

    /// Every intact entry, oldest first (by file time), and the damaged files that name their
    /// job. A damaged file whose name identifies no job is removed here, with a warning.
    pub fn load(&self) -> Loaded {
        let mut loaded = Loaded::default();
        let Ok(read) = std::fs::read_dir(&self.dir) else {
            return loaded;
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
                None => match name_of(&path) {
                    Some(d) => {
                        tracing::warn!(path = %path.display(), id = %d.id, "corrupt journal file: its job is recorded as lost");
                        loaded.damaged.push(d);
                    }
                    None => {
                        tracing::warn!(path = %path.display(), "corrupt journal file with a foreign name removed");
                        let _ = std::fs::remove_file(&path);
                    }
                },
            }
        }
        found.sort_by_key(|(t, _)| *t);
        loaded.entries = found.into_iter().map(|(_, e)| e).collect();
        loaded
    }
}

/// The job a journal file is named after (`<id>.<hex tenant>.job`), if the name is one this
/// journal writes: a 64-hex-digit id and a tenant that decodes to UTF-8.
fn name_of(path: &Path) -> Option<Damaged> {
    let stem = path.file_stem()?.to_str()?;
    let (id, tenant) = stem.split_once('.')?;
    let is_id = id.len() == 64
        && id
            .bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b));
    if !is_id {
        return None;
    }
    let tenant = String::from_utf8(hex::decode(tenant).ok()?).ok()?;
    Some(Damaged {
        tenant,
        id: id.to_string(),
    })
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
    fn entries_round_trip_and_corruption_names_the_lost_job() {
        let dir = tempfile::tempdir().unwrap();
        let j = Journal::open(dir.path()).unwrap();
        let (a, b) = ("a".repeat(64), "b".repeat(64));
        j.record(&entry("", &a)).unwrap();
        j.record(&entry("fleet-a", &a)).unwrap();
        let mut got = j.load().entries;
        got.sort_by(|x, y| x.tenant.cmp(&y.tenant));
        assert_eq!(got, vec![entry("", &a), entry("fleet-a", &a)]);
        j.remove("", &a);
        assert_eq!(j.load().entries, vec![entry("fleet-a", &a)]);
        // Flip one byte: the file fails its checksum; its name still says whose job it was,
        // and it stays until the loss is recorded.
        let path = j.path("fleet-a", &a);
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[12] ^= 1;
        std::fs::write(&path, bytes).unwrap();
        let loaded = j.load();
        assert!(loaded.entries.is_empty());
        assert_eq!(
            loaded.damaged,
            vec![Damaged {
                tenant: "fleet-a".into(),
                id: a.clone()
            }]
        );
        assert!(path.exists());
        j.remove("fleet-a", &a);
        // A damaged file under a name this journal never writes has no job to report.
        let foreign = dir.path().join(format!("{b}.zz.job"));
        std::fs::write(&foreign, b"junk").unwrap();
        let loaded = j.load();
        assert!(loaded.entries.is_empty() && loaded.damaged.is_empty());
        assert!(!foreign.exists());
        assert_eq!(decode(&encode(&entry("t", &b))), Some(entry("t", &b)));
        assert_eq!(decode(b"MURKJOB1"), None);
    }
}
