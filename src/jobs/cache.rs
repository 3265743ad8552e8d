//! Result cache keyed by job id: an in-memory LRU bounded by bytes, plus an optional directory so
//! results survive a restart. Entries on disk carry a checksum; a corrupt file is a miss, not an
//! error, and is removed.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use sha2::{Digest, Sha256};

use super::state::ResultBytes;

const DISK_MAGIC: &[u8; 8] = b"MURKRES1";

#[derive(Default)]
struct Lru {
    entries: HashMap<String, (ResultBytes, u64)>,
    by_tick: BTreeMap<u64, String>,
    bytes: u64,
    tick: u64,
}

/// Counters for observability and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CacheStats {
    /// Lookups answered from memory.
    pub memory_hits: u64,
    /// Lookups answered from the disk directory.
    pub disk_hits: u64,
    /// Lookups that found nothing.
    pub misses: u64,
    /// Bytes currently held in memory.
    pub memory_bytes: u64,
    /// Entries currently held in memory.
    pub memory_entries: u64,
}

/// Memory + disk result cache.
pub struct ResultCache {
    max_bytes: u64,
    dir: Option<PathBuf>,
    lru: Mutex<Lru>,
    memory_hits: AtomicU64,
    disk_hits: AtomicU64,
    misses: AtomicU64,
}

impl ResultCache {
    /// A cache holding at most `max_bytes` of results in memory, and everything in `dir` if given.
    /// Creates `dir` when missing.
    pub fn new(max_bytes: u64, dir: Option<PathBuf>) -> std::io::Result<Self> {
        if let Some(d) = &dir {
            std::fs::create_dir_all(d)?;
        }
        Ok(Self {
            max_bytes,
            dir,
            lru: Mutex::new(Lru::default()),
            memory_hits: AtomicU64::new(0),
            disk_hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
        })
    }

    /// Looks `id` up in memory, then on disk (promoting a disk hit into memory).
    pub fn get(&self, id: &str) -> Option<ResultBytes> {
        if let Some(v) = self.get_memory(id) {
            self.memory_hits.fetch_add(1, Ordering::Relaxed);
            return Some(v);
        }
        if let Some(v) = self.get_disk(id) {
            self.disk_hits.fetch_add(1, Ordering::Relaxed);
            self.put_memory(id, v.clone());
            return Some(v);
        }
        self.misses.fetch_add(1, Ordering::Relaxed);
        None
    }

    /// Stores a result in memory and, if configured, on disk. Disk failures are logged, not fatal:
    /// the result is still served from memory.
    pub fn put(&self, id: &str, value: ResultBytes) {
        if let Some(path) = self.disk_path(id) {
            if let Err(e) = write_disk(&path, &value) {
                tracing::warn!(%id, error = %e, "could not write result to the cache directory");
            }
        }
        self.put_memory(id, value);
    }

    /// Current counters.
    pub fn stats(&self) -> CacheStats {
        let (bytes, entries) = match self.lru.lock() {
            Ok(l) => (l.bytes, l.entries.len() as u64),
            Err(_) => (0, 0),
        };
        CacheStats {
            memory_hits: self.memory_hits.load(Ordering::Relaxed),
            disk_hits: self.disk_hits.load(Ordering::Relaxed),
            misses: self.misses.load(Ordering::Relaxed),
            memory_bytes: bytes,
            memory_entries: entries,
        }
    }

    fn get_memory(&self, id: &str) -> Option<ResultBytes> {
        let mut guard = self.lru.lock().ok()?;
        let lru = &mut *guard;
        lru.tick += 1;
        let tick = lru.tick;
        let (value, old_tick) = lru.entries.get_mut(id)?;
        let value = value.clone();
        lru.by_tick.remove(old_tick);
        *old_tick = tick;
        lru.by_tick.insert(tick, id.to_string());
        Some(value)
    }

    fn put_memory(&self, id: &str, value: ResultBytes) {
        let size = value.len() as u64;
        if size > self.max_bytes {
            return;
        }
        let Ok(mut guard) = self.lru.lock() else {
            return;
        };
        let lru = &mut *guard;
        lru.tick += 1;
        let tick = lru.tick;
        if let Some((old, old_tick)) = lru.entries.insert(id.to_string(), (value, tick)) {
            lru.bytes -= old.len() as u64;
            lru.by_tick.remove(&old_tick);
        }
        lru.by_tick.insert(tick, id.to_string());
        lru.bytes += size;
        while lru.bytes > self.max_bytes {
            let Some((_, victim)) = lru.by_tick.pop_first() else {
                break;
            };
            if let Some((v, _)) = lru.entries.remove(&victim) {
                lru.bytes -= v.len() as u64;
            }
        }
    }

    fn disk_path(&self, id: &str) -> Option<PathBuf> {
        // Ids are hex hashes; anything else never touches the file system.
        if id.is_empty() || id.len() > 128 || !id.bytes().all(|b| b.is_ascii_hexdigit()) {
            return None;
        }
        self.dir.as_ref().map(|d| d.join(format!("{id}.murkres")))
    }

    fn get_disk(&self, id: &str) -> Option<ResultBytes> {
        let path = self.disk_path(id)?;
        let bytes = std::fs::read(&path).ok()?;
        match parse_disk(&bytes) {
            Some(payload) => Some(Arc::new(payload.to_vec())),
            None => {
                tracing::warn!(path = %path.display(), "corrupt cache file ignored and removed");
                let _ = std::fs::remove_file(&path);
                None
            }
        }
    }
}

fn parse_disk(bytes: &[u8]) -> Option<&[u8]> {
    let rest = bytes.strip_prefix(DISK_MAGIC.as_slice())?;
    if rest.len() < 32 {
        return None;
    }
    let (sum, payload) = rest.split_at(32);
    (Sha256::digest(payload).as_slice() == sum).then_some(payload)
}

fn write_disk(path: &Path, payload: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    let mut buf = Vec::with_capacity(payload.len() + 40);
    buf.extend_from_slice(DISK_MAGIC);
    buf.extend_from_slice(&Sha256::digest(payload));
    buf.extend_from_slice(payload);
    std::fs::write(&tmp, &buf)?;
    // Rename is atomic, so a crash never leaves a half-written entry under the final name.
    std::fs::rename(&tmp, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn val(n: usize, b: u8) -> ResultBytes {
        Arc::new(vec![b; n])
    }

    #[test]
    fn evicts_least_recently_used_by_bytes() {
        let c = ResultCache::new(100, None).unwrap();
        c.put("a", val(40, 1));
        c.put("b", val(40, 2));
        assert!(c.get("a").is_some()); // a is now more recent than b
        c.put("c", val(40, 3));
        assert!(c.get("b").is_none());
        assert!(c.get("a").is_some() && c.get("c").is_some());
        assert!(c.stats().memory_bytes <= 100);
        c.put("huge", val(1000, 4));
        assert!(
            c.get("huge").is_none(),
            "entries above the budget are not kept"
        );
    }

    #[test]
    fn disk_survives_new_instance_and_rejects_corruption() {
        let dir = tempfile::tempdir().unwrap();
        let id = "abcdef0123";
        {
            let c = ResultCache::new(1 << 20, Some(dir.path().to_path_buf())).unwrap();
            c.put(id, val(10, 7));
        }
        let c = ResultCache::new(1 << 20, Some(dir.path().to_path_buf())).unwrap();
        assert_eq!(c.get(id).unwrap().as_slice(), &[7u8; 10]);
        assert_eq!(c.stats().disk_hits, 1);

        let path = dir.path().join("fedcba.murkres");
        std::fs::write(&path, b"MURKRES1garbage").unwrap();
        assert!(c.get("fedcba").is_none());
        assert!(!path.exists(), "corrupt entry removed");
        assert!(
            c.get("../etc/passwd").is_none(),
            "non-hex ids never reach the disk"
        );
    }
}
