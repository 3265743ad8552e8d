//! The Lua scripts that change job records. Each runs atomically inside Redis, so two replicas
//! never interleave a check with the write it guards (the global queue bound, the start of a
//! claimed job, a cancel racing a finish).
//!
//! A record is the hash `{prefix}:job:{tenant}:{id}` with fields `tenant id method state
//! progress stage create_ms start_ms end_ms cached gen entry owner attempts version cancel
//! detached err_kind err_a err_b` and one `w:{view}` field per replica view holding unary
//! waiters (`seq:count`). `gen` numbers each computation of the record: a resubmission after a
//! cancel starts a new generation, and a replica finishing an older one changes nothing.

use redis::Script;

/// Shared helpers, prepended to every script.
const PRELUDE: &str = r#"
local function bump(rec) redis.call('HINCRBY', rec, 'version', 1) end
local function live(rec)
  local st = redis.call('HGET', rec, 'state')
  return st == 'queued' or st == 'running'
end
-- Acknowledges and deletes a claimed stream entry; true when the record is still live and in
-- the generation that entry computed.
local function settle(rec, stream, group, entry, gen)
  redis.call('XACK', stream, group, entry)
  redis.call('XDEL', stream, entry)
  return redis.call('HGET', rec, 'gen') == gen and live(rec)
end
local function close(rec, state, now, kind, a, b, ttl)
  if state == 'succeeded' then
    redis.call('HSET', rec, 'state', state, 'end_ms', now, 'progress', '1', 'stage', 'done')
  else
    redis.call('HSET', rec, 'state', state, 'end_ms', now, 'stage', state,
      'err_kind', kind, 'err_a', a, 'err_b', b)
  end
  bump(rec)
  redis.call('EXPIRE', rec, ttl)
end
local function cancel(rec, queued, now, ttl, channel, member)
  local st = redis.call('HGET', rec, 'state')
  if not st then return 'missing' end
  if st == 'queued' then
    redis.call('HSET', rec, 'cancel', '1')
    redis.call('ZREM', queued, member)
    close(rec, 'cancelled', now, 'cancelled', '', '', ttl)
    redis.call('PUBLISH', channel, 'u\t' .. member)
    return 'cancelled'
  elseif st == 'running' then
    redis.call('HSET', rec, 'cancel', '1')
    bump(rec)
    redis.call('PUBLISH', channel, 'c\t' .. member)
    return 'signalled'
  end
  return 'terminal'
end
local function trim(list, keep)
  local n = redis.call('ZCARD', list)
  if n > keep then redis.call('ZREMRANGEBYRANK', list, 0, n - keep - 1) end
end
"#;

/// KEYS: record, queued set, tenant's job list, stream, generation counter.
/// ARGV: tenant, id, method, now_ms, capacity, request, max_records, channel, force.
/// Returns `{'existing'}`, `{'full', depth}` or `{'queued', gen}`.
const SUBMIT: &str = r#"
local st = redis.call('HGET', KEYS[1], 'state')
if st == 'succeeded' and ARGV[9] ~= '1' then return {'existing'} end
if (st == 'queued' or st == 'running') and redis.call('HGET', KEYS[1], 'cancel') ~= '1' then
  return {'existing'}
end
local depth = redis.call('ZCARD', KEYS[2])
if depth >= tonumber(ARGV[5]) then return {'full', depth} end
local gen = redis.call('INCR', KEYS[5])
local member = ARGV[1] .. '\t' .. ARGV[2]
local entry = redis.call('XADD', KEYS[4], '*', 'tenant', ARGV[1], 'id', ARGV[2],
  'method', ARGV[3], 'gen', gen, 'request', ARGV[6])
redis.call('DEL', KEYS[1])
redis.call('HSET', KEYS[1], 'tenant', ARGV[1], 'id', ARGV[2], 'method', ARGV[3],
  'state', 'queued', 'progress', '0', 'stage', 'queued', 'create_ms', ARGV[4], 'gen', gen,
  'entry', entry, 'version', '1', 'attempts', '0')
redis.call('ZADD', KEYS[2], ARGV[4], member)
redis.call('ZADD', KEYS[3], ARGV[4], ARGV[2])
trim(KEYS[3], tonumber(ARGV[7]))
redis.call('PUBLISH', ARGV[8], 'u\t' .. member)
return {'queued', gen}
"#;

/// A cached result becomes `tenant`'s succeeded record, unless a live or succeeded one exists.
/// KEYS: record, tenant's job list. ARGV: tenant, id, method, now_ms, ttl_s, max_records,
/// channel. Returns 1 when written.
const CACHED: &str = r#"
local st = redis.call('HGET', KEYS[1], 'state')
if st == 'succeeded' then return 0 end
if (st == 'queued' or st == 'running') and redis.call('HGET', KEYS[1], 'cancel') ~= '1' then
  return 0
end
redis.call('DEL', KEYS[1])
redis.call('HSET', KEYS[1], 'tenant', ARGV[1], 'id', ARGV[2], 'method', ARGV[3],
  'state', 'succeeded', 'progress', '1', 'stage', 'done', 'create_ms', ARGV[4],
  'end_ms', ARGV[4], 'cached', '1', 'gen', '0', 'version', '1')
redis.call('EXPIRE', KEYS[1], ARGV[5])
redis.call('ZADD', KEYS[2], ARGV[4], ARGV[2])
trim(KEYS[2], tonumber(ARGV[6]))
redis.call('PUBLISH', ARGV[7], 'u\t' .. ARGV[1] .. '\t' .. ARGV[2])
return 1
"#;

/// A replica took a stream entry: the record moves to running, unless it is of another
/// generation, ended, or was cancelled meanwhile, or its replicas died on it too often.
/// KEYS: record, queued set. ARGV: tenant, id, gen, owner, now_ms, max_attempts, channel, ttl_s.
/// Returns `run`, `stale`, `cancelled` or `failed`.
const START: &str = r#"
local member = ARGV[1] .. '\t' .. ARGV[2]
if redis.call('HGET', KEYS[1], 'gen') ~= ARGV[3] or not live(KEYS[1]) then return 'stale' end
redis.call('ZREM', KEYS[2], member)
if redis.call('HGET', KEYS[1], 'cancel') == '1' then
  close(KEYS[1], 'cancelled', ARGV[5], 'cancelled', '', '', ARGV[8])
  redis.call('PUBLISH', ARGV[7], 'u\t' .. member)
  return 'cancelled'
end
local attempts = redis.call('HINCRBY', KEYS[1], 'attempts', 1)
if attempts > tonumber(ARGV[6]) then
  close(KEYS[1], 'failed', ARGV[5], 'internal', 'the job was started ' .. (attempts - 1) ..
    ' times and each time its replica stopped before finishing it', '', ARGV[8])
  redis.call('PUBLISH', ARGV[7], 'u\t' .. member)
  return 'failed'
end
redis.call('HSET', KEYS[1], 'state', 'running', 'owner', ARGV[4], 'start_ms', ARGV[5],
  'stage', 'starting', 'progress', '0')
bump(KEYS[1])
redis.call('PUBLISH', ARGV[7], 'u\t' .. member)
return 'run'
"#;

/// Progress of a running job. KEYS: record. ARGV: gen, progress, stage, channel, member.
/// Returns 1 when cancellation was requested, 0 to go on, -1 when the record is no longer this
/// computation's (stop).
const PROGRESS: &str = r#"
if redis.call('HGET', KEYS[1], 'gen') ~= ARGV[1] or redis.call('HGET', KEYS[1], 'state') ~= 'running' then
  return -1
end
redis.call('HSET', KEYS[1], 'progress', ARGV[2], 'stage', ARGV[3])
bump(KEYS[1])
redis.call('PUBLISH', ARGV[4], 'u\t' .. ARGV[5])
if redis.call('HGET', KEYS[1], 'cancel') == '1' then return 1 end
return 0
"#;

/// Renews the lease on a running job's stream entry (resets its idle time, so no other replica
/// reclaims it) if this replica still holds it. KEYS: stream, record. ARGV: group, entry,
/// owner, gen. Returns 1 when cancellation was requested, 0 to go on, -1 when the lease or the
/// record was lost (stop).
const HEARTBEAT: &str = r#"
local p = redis.call('XPENDING', KEYS[1], ARGV[1], ARGV[2], ARGV[2], 1, ARGV[3])
if #p == 0 then return -1 end
redis.call('XCLAIM', KEYS[1], ARGV[1], ARGV[3], 0, ARGV[2], 'JUSTID')
if redis.call('HGET', KEYS[2], 'gen') ~= ARGV[4] or not live(KEYS[2]) then return -1 end
if redis.call('HGET', KEYS[2], 'cancel') == '1' then return 1 end
return 0
"#;

/// Ends a computation: acknowledges and deletes its stream entry, and closes the record if it
/// is still this generation's. KEYS: record, stream, queued set. ARGV: gen, entry, group, state,
/// now_ms, err_kind, err_a, err_b, ttl_s, channel, member. Returns 1 when the record changed.
const FINISH: &str = r#"
if not settle(KEYS[1], KEYS[2], ARGV[3], ARGV[2], ARGV[1]) then return 0 end
redis.call('ZREM', KEYS[3], ARGV[11])
close(KEYS[1], ARGV[4], ARGV[5], ARGV[6], ARGV[7], ARGV[8], ARGV[9])
redis.call('PUBLISH', ARGV[10], 'u\t' .. ARGV[11])
return 1
"#;

/// Hands a job a stopping replica did not finish back to the queue (a fresh entry, outside the
/// queue bound: it was accepted already; not counted as a failed attempt). KEYS: record,
/// stream, queued set. ARGV: gen, entry, group, now_ms, channel, member, tenant, id, method,
/// request, ttl_s. Returns 1 when re-queued.
const REQUEUE: &str = r#"
if not settle(KEYS[1], KEYS[2], ARGV[3], ARGV[2], ARGV[1]) then return 0 end
if redis.call('HGET', KEYS[1], 'cancel') == '1' then
  close(KEYS[1], 'cancelled', ARGV[4], 'cancelled', '', '', ARGV[11])
  redis.call('PUBLISH', ARGV[5], 'u\t' .. ARGV[6])
  return 0
end
local entry = redis.call('XADD', KEYS[2], '*', 'tenant', ARGV[7], 'id', ARGV[8],
  'method', ARGV[9], 'gen', ARGV[1], 'request', ARGV[10])
redis.call('HSET', KEYS[1], 'state', 'queued', 'stage', 'queued', 'progress', '0',
  'entry', entry, 'owner', '')
redis.call('HINCRBY', KEYS[1], 'attempts', -1)
redis.call('ZADD', KEYS[3], ARGV[4], ARGV[6])
bump(KEYS[1])
redis.call('PUBLISH', ARGV[5], 'u\t' .. ARGV[6])
return 1
"#;

/// KEYS: record, queued set. ARGV: now_ms, ttl_s, channel, member.
/// Returns `missing`, `cancelled` (it was queued), `signalled` (running: its replica stops it)
/// or `terminal`.
const CANCEL: &str = r#"
return cancel(KEYS[1], KEYS[2], ARGV[1], ARGV[2], ARGV[3], ARGV[4])
"#;

/// One replica view's count of unary waiters; the job is cancelled when no view has any and
/// no one detached it. KEYS: record, queued set. ARGV: field, seq, count, now_ms, ttl_s,
/// channel, member. Returns 1 when it cancelled the job.
const WAITERS: &str = r#"
if not live(KEYS[1]) then return 0 end
local cur = redis.call('HGET', KEYS[1], ARGV[1])
if cur then
  local s = tonumber(string.match(cur, '^(%d+):'))
  if s and s >= tonumber(ARGV[2]) then return 0 end
end
redis.call('HSET', KEYS[1], ARGV[1], ARGV[2] .. ':' .. ARGV[3])
if tonumber(ARGV[3]) > 0 or redis.call('HGET', KEYS[1], 'detached') == '1'
  or redis.call('HGET', KEYS[1], 'cancel') == '1' then
  return 0
end
local all = redis.call('HGETALL', KEYS[1])
for i = 1, #all, 2 do
  if string.sub(all[i], 1, 2) == 'w:' then
    local c = tonumber(string.match(all[i + 1], ':(%d+)$'))
    if c and c > 0 then return 0 end
  end
end
cancel(KEYS[1], KEYS[2], ARGV[4], ARGV[5], ARGV[6], ARGV[7])
return 1
"#;

/// KEYS: record. Marks a job as owned by the Jobs API (never cancelled for lack of waiters).
const DETACH: &str = r#"
if redis.call('EXISTS', KEYS[1]) == 1 then redis.call('HSET', KEYS[1], 'detached', '1') end
return 0
"#;

/// The compiled scripts (Redis caches them by SHA-1; `invoke_async` loads them on first use).
pub(super) struct Scripts {
    pub submit: Script,
    pub cached: Script,
    pub start: Script,
    pub progress: Script,
    pub heartbeat: Script,
    pub finish: Script,
    pub requeue: Script,
    pub cancel: Script,
    pub waiters: Script,
    pub detach: Script,
}

impl Scripts {
    pub(super) fn new() -> Self {
        let s = |body: &str| Script::new(&format!("{PRELUDE}\n{body}"));
        Self {
            submit: s(SUBMIT),
            cached: s(CACHED),
            start: s(START),
            progress: s(PROGRESS),
            heartbeat: s(HEARTBEAT),
            finish: s(FINISH),
            requeue: s(REQUEUE),
            cancel: s(CANCEL),
            waiters: s(WAITERS),
            detach: s(DETACH),
        }
    }
}
