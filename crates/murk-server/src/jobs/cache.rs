//! Result cache keyed by job id: an in-memory LRU bounded by bytes, plus an optional directory so
//! results survive a restart.
//!
//! On disk each entry is `<id>.murkres`: a header binding the entry to its job id (magic, id
//! length, id, SHA-256 over id and payload), then the payload. A file that fails the check —
//! truncated, bit-flipped, or copied under another job's name — is a miss, not an error, and is
//! removed. Writes go to a temporary file that is fsynced, renamed over the final name and the
//! directory fsynced, so a crash leaves either the whole entry or none. The directory is bounded
//! (`disk_max_bytes`): the least recently written or read entries go first. At start a
//! background thread verifies every entry (removing corrupt ones and stray temporary files) and
//! counts the bytes.

use std::collections::{BTreeMap, HashMap};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use sha2::{Digest, Sha256};

use super::state::ResultBytes;

/// Version 2: the header binds the job id (version 1 had the payload's checksum only, so a file
/// copied under another id was served as that job's result).
const DISK_MAGIC: &[u8; 8] = b"MURKRES2";
const EXTENSION: &str = "murkres";

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
    /// Bytes of entries in the cache directory (as far as the startup scan has counted).
    pub disk_bytes: u64,
    /// Files removed because they failed the id/checksum check.
    pub disk_rejected: u64,
}

/// The directory part: a bounded set of entry files, least recently used first out.
#[derive(Default)]
struct DiskIndex {
    /// id → (file bytes, tick of last use).
    entries: HashMap<String, (u64, u64)>,
    by_tick: BTreeMap<u64, String>,
    bytes: u64,
    tick: u64,
}

impl DiskIndex {
    fn touch(&mut self, id: &str, size: u64) {
        self.tick += 1;
        let tick = self.tick;
        if let Some((old_size, old_tick)) = self.entries.insert(id.to_string(), (size, tick)) {
            self.by_tick.remove(&old_tick);
            self.bytes -= old_size;
        }
        self.by_tick.insert(tick, id.to_string());
        self.bytes += size;
    }

    fn forget(&mut self, id: &str) {
        if let Some((size, tick)) = self.entries.remove(id) {
            self.by_tick.remove(&tick);
            self.bytes -= size;
        }
    }
}

/// Memory + disk result cache.
pub struct ResultCache {
    max_bytes: u64,
    dir: Option<PathBuf>,
    disk_max_bytes: u64,
    lru: Mutex<Lru>,
    disk: Arc<Mutex<DiskIndex>>,
    memory_hits: AtomicU64,
    disk_hits: AtomicU64,
    misses: AtomicU64,
    disk_rejected: Arc<AtomicU64>,
}

impl ResultCache {
    /// A cache holding at most `max_bytes` of results in memory, and everything in `dir` if given.
    /// Creates `dir` when missing.
    pub fn new(max_bytes: u64, dir: Option<PathBuf>) -> std::io::Result<Self> {
        Self::with_disk_bound(max_bytes, dir, u64::MAX)
    }

    /// [`ResultCache::new`] whose directory holds at most `disk_max_bytes` of entry files, and
    /// whose existing entries are verified by a background scan.
    pub fn with_disk_bound(
        max_bytes: u64,
        dir: Option<PathBuf>,
        disk_max_bytes: u64,
    ) -> std::io::Result<Self> {
        if let Some(d) = &dir {
            std::fs::create_dir_all(d)?;
        }
        let cache = Self {
            max_bytes,
            dir,
            disk_max_bytes,
            lru: Mutex::new(Lru::default()),
            disk: Arc::new(Mutex::new(DiskIndex::default())),
            memory_hits: AtomicU64::new(0),
            disk_hits: AtomicU64::new(0),
            misses: AtomicU64::new(0),
            disk_rejected: Arc::new(AtomicU64::new(0)),
        };
        if let Some(d) = cache.dir.clone() {
            let (index, rejected, bound) = (
                cache.disk.clone(),
                cache.disk_rejected.clone(),
                disk_max_bytes,
            );
            std::thread::Builder::new()
                .name("murk-cache-scan".into())
                .spawn(move || scan_dir(&d, &index, &rejected, bound))?;
        }
        Ok(cache)
    }

    /// Waits until the startup scan has indexed the directory (tests).
    #[cfg(test)]
    fn wait_for_scan(&self) {
        while self.scanning() {
            std::thread::yield_now();
        }
    }

    #[cfg(test)]
    fn scanning(&self) -> bool {
        self.dir.as_ref().is_some_and(|d| {
            std::fs::read_dir(d).is_ok_and(|rd| {
                let files = rd
                    .filter_map(|e| e.ok())
                    .filter(|e| e.path().extension().is_some_and(|x| x == EXTENSION))
                    .count();
                self.disk.lock().map_or(0, |i| i.entries.len()) < files
            })
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
            match write_disk(&path, id, &value) {
                Ok(size) => self.account_disk(id, size),
                Err(e) => {
                    tracing::warn!(%id, error = %e, "could not write result to the cache directory")
                }
            }
        }
        self.put_memory(id, value);
    }

    /// Records a file of `size` bytes for `id` and removes the least recently used files beyond
    /// the directory's bound.
    fn account_disk(&self, id: &str, size: u64) {
        let Ok(mut index) = self.disk.lock() else {
            return;
        };
        index.touch(id, size);
        evict_disk(
            &mut index,
            self.dir.as_deref(),
            self.disk_max_bytes,
            Some(id),
        );
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
            disk_bytes: self.disk.lock().map_or(0, |i| i.bytes),
            disk_rejected: self.disk_rejected.load(Ordering::Relaxed),
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
        self.dir
            .as_ref()
            .map(|d| d.join(format!("{id}.{EXTENSION}")))
    }

    fn get_disk(&self, id: &str) -> Option<ResultBytes> {
        let path = self.disk_path(id)?;
        let bytes = std::fs::read(&path).ok()?;
        match parse_disk(&bytes, id) {
            Some(payload) => {
                if let Ok(mut index) = self.disk.lock() {
                    index.touch(id, bytes.len() as u64);
                }
                Some(Arc::new(payload.to_vec()))
            }
            None => {
                tracing::warn!(path = %path.display(), "cache file fails its id/checksum check; removed");
                self.disk_rejected.fetch_add(1, Ordering::Relaxed);
                let _ = std::fs::remove_file(&path);
                if let Ok(mut index) = self.disk.lock() {
                    index.forget(id);
                }
                None
            }
        }
    }
}

/// The payload of an entry file if its header names `id` and its checksum holds.
fn parse_disk<'a>(bytes: &'a [u8], id: &str) -> Option<&'a [u8]> {
    let rest = bytes.strip_prefix(DISK_MAGIC.as_slice())?;
    let (&len, rest) = rest.split_first()?;
    let len = usize::from(len);
    if rest.len() < len + 32 {
        return None;
    }
    let (stored_id, rest) = rest.split_at(len);
    let (sum, payload) = rest.split_at(32);
    if stored_id != id.as_bytes() {
        return None;
    }
    (digest(stored_id, payload).as_slice() == sum).then_some(payload)
}

/// SHA-256 over the id's length, the id and the payload.
fn digest(id: &[u8], payload: &[u8]) -> [u8; 32] {
    let mut h = Sha256::new();
    h.update([id.len() as u8]);
    h.update(id);
    h.update(payload);
    h.finalize().into()
}

/// Writes an entry atomically and durably; returns the file's size.
fn write_disk(path: &Path, id: &str, payload: &[u8]) -> std::io::Result<u64> {
    let id = id.as_bytes();
    debug_assert!(id.len() <= 128, "disk_path admits ids of at most 128 bytes");
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    let mut f = std::fs::File::create(&tmp)?;
    f.write_all(DISK_MAGIC)?;
    f.write_all(&[id.len() as u8])?;
    f.write_all(id)?;
    f.write_all(&digest(id, payload))?;
    f.write_all(payload)?;
    // Data on disk before the name points at it: a crash leaves the old state or the new one.
    f.sync_all()?;
    drop(f);
    std::fs::rename(&tmp, path)?;
    if let Some(dir) = path.parent() {
        // The rename itself is durable once the directory is synced.
        std::fs::File::open(dir)?.sync_all()?;
    }
    Ok((DISK_MAGIC.len() + 1 + id.len() + 32 + payload.len()) as u64)
}

/// Removes the least recently used entry files until the directory fits `max_bytes`, sparing
/// `keep` (the entry just written).
fn evict_disk(index: &mut DiskIndex, dir: Option<&Path>, max_bytes: u64, keep: Option<&str>) {
    let Some(dir) = dir else { return };
    while index.bytes > max_bytes {
        let Some(victim) = index
            .by_tick
            .values()
            .find(|v| Some(v.as_str()) != keep)
            .cloned()
        else {
            break;
        };
        let _ = std::fs::remove_file(dir.join(format!("{victim}.{EXTENSION}")));
        index.forget(&victim);
    }
}

/// The startup scan: verifies every entry file, removes corrupt ones and stray temporary files,
/// indexes the rest oldest-first, and applies the directory bound.
fn scan_dir(dir: &Path, index: &Mutex<DiskIndex>, rejected: &AtomicU64, max_bytes: u64) {
    let Ok(read) = std::fs::read_dir(dir) else {
        return;
    };
    let mut found: Vec<(std::time::SystemTime, String, u64)> = Vec::new();
    for entry in read.filter_map(|e| e.ok()) {
        let path = entry.path();
        let Some(ext) = path.extension().and_then(|e| e.to_str()) else {
            continue;
        };
        if ext.starts_with("tmp") {
            // A write interrupted by a crash: another process's (never ours, which may be
            // writing it now) and old enough that no live writer can still be on it.
            let ours = ext == format!("tmp{}", std::process::id());
            let stale = entry
                .metadata()
                .and_then(|m| m.modified())
                .ok()
                .and_then(|t| t.elapsed().ok())
                .is_some_and(|age| age > std::time::Duration::from_secs(60));
            if !ours && stale {
                let _ = std::fs::remove_file(&path);
            }
            continue;
        }
        if ext != EXTENSION {
            continue;
        }
        let Some(id) = path
            .file_stem()
            .and_then(|s| s.to_str())
            .map(str::to_string)
        else {
            continue;
        };
        let ok = std::fs::read(&path)
            .ok()
            .is_some_and(|b| parse_disk(&b, &id).is_some());
        if !ok {
            tracing::warn!(path = %path.display(), "cache scan: entry fails its id/checksum check; removed");
            rejected.fetch_add(1, Ordering::Relaxed);
            let _ = std::fs::remove_file(&path);
            continue;
        }
        let meta = entry.metadata().ok();
        let mtime = meta
            .as_ref()
            .and_then(|m| m.modified().ok())
            .unwrap_or(std::time::UNIX_EPOCH);
        found.push((mtime, id, meta.map_or(0, |m| m.len())));
    }
    found.sort();
    let Ok(mut index) = index.lock() else { return };
    // Oldest first, so the least recently written are the first to go; entries written since
    // start (already indexed) keep their newer ticks.
    let fresh: Vec<_> = found
        .into_iter()
        .filter(|(_, id, _)| !index.entries.contains_key(id))
        .collect();
    let mut rebuilt = DiskIndex::default();
    for (_, id, size) in &fresh {
        rebuilt.touch(id, *size);
    }
    let newer: Vec<(u64, String)> = index
        .by_tick
        .iter()
        .map(|(t, id)| (*t, id.clone()))
        .collect();
    for (_, id) in newer {
        let size = index.entries.get(&id).map_or(0, |e| e.0);
        rebuilt.touch(&id, size);
    }
    *index = rebuilt;
    evict_disk(&mut index, Some(dir), max_bytes, None);
    tracing::info!(
        entries = index.entries.len(),
        bytes = index.bytes,
        "cache directory scanned"
    );
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
        std::fs::write(&path, b"MURKRES2garbage").unwrap();
        assert!(c.get("fedcba").is_none());
        assert!(!path.exists(), "corrupt entry removed");
        assert!(
            c.get("../etc/passwd").is_none(),
            "non-hex ids never reach the disk"
        );
    }

    #[test]
    fn a_file_copied_under_another_id_is_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let c = ResultCache::new(1 << 20, Some(dir.path().to_path_buf())).unwrap();
        c.put("aa11", val(10, 1));
        c.put("bb22", val(10, 2));
        // Swap: bb22's name now holds aa11's (valid, checksummed) entry.
        std::fs::copy(
            dir.path().join("aa11.murkres"),
            dir.path().join("bb22.murkres"),
        )
        .unwrap();
        let fresh = ResultCache::new(1 << 20, Some(dir.path().to_path_buf())).unwrap();
        fresh.wait_for_scan();
        assert!(
            fresh.get("bb22").is_none(),
            "not served as another job's result"
        );
        assert!(!dir.path().join("bb22.murkres").exists());
        assert_eq!(fresh.get("aa11").unwrap().as_slice(), &[1u8; 10]);
        assert!(fresh.stats().disk_rejected >= 1);
    }

    #[test]
    fn the_directory_is_bounded_least_recently_used_first() {
        let dir = tempfile::tempdir().unwrap();
        let entry = (DISK_MAGIC.len() + 1 + 4 + 32 + 100) as u64;
        let c = ResultCache::with_disk_bound(1 << 20, Some(dir.path().to_path_buf()), 3 * entry)
            .unwrap();
        c.wait_for_scan();
        for id in ["0001", "0002", "0003"] {
            c.put(id, val(100, 1));
        }
        assert!(c.get_disk("0001").is_some()); // 0001 is now more recent than 0002
        c.put("0004", val(100, 4));
        assert!(
            !dir.path().join("0002.murkres").exists(),
            "LRU entry evicted"
        );
        for id in ["0001", "0003", "0004"] {
            assert!(dir.path().join(format!("{id}.murkres")).exists(), "{id}");
        }
        assert_eq!(c.stats().disk_bytes, 3 * entry);
    }

    #[test]
    fn the_startup_scan_removes_corrupt_and_temporary_files_and_applies_the_bound() {
        let dir = tempfile::tempdir().unwrap();
        {
            let c = ResultCache::new(1 << 20, Some(dir.path().to_path_buf())).unwrap();
            for id in ["0a", "0b", "0c"] {
                c.put(id, val(50, 3));
            }
        }
        let mut bytes = std::fs::read(dir.path().join("0b.murkres")).unwrap();
        let last = bytes.len() - 1;
        bytes[last] ^= 1;
        std::fs::write(dir.path().join("0b.murkres"), bytes).unwrap();
        let stray = std::fs::File::create(dir.path().join("0d.tmp1")).unwrap();
        stray
            .set_modified(std::time::UNIX_EPOCH + std::time::Duration::from_secs(1_000_000))
            .unwrap();
        drop(stray);
        let entry = (DISK_MAGIC.len() + 1 + 2 + 32 + 50) as u64;
        let c =
            ResultCache::with_disk_bound(1 << 20, Some(dir.path().to_path_buf()), entry).unwrap();
        // The scan runs in the background; wait until it has removed the bad files.
        while dir.path().join("0b.murkres").exists() || dir.path().join("0d.tmp1").exists() {
            std::thread::yield_now();
        }
        c.wait_for_scan();
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .filter_map(|e| e.ok())
            .collect();
        assert_eq!(left.len(), 1, "bound of one entry applied");
        assert_eq!(c.stats().disk_rejected, 1);
    }
}
