//! Entries of the work stream as this replica reads them: one entry is one job to compute.

use redis::Value;

/// One stream entry: a job to compute.
#[derive(Debug)]
pub(super) struct Claimed {
    /// The entry's id in the stream: what the lease and the acknowledgement name.
    pub(super) entry: String,
    pub(super) tenant: String,
    pub(super) id: String,
    pub(super) method: String,
    /// The record generation the entry was queued for.
    pub(super) gen: String,
    /// The canonical request, from which the work is rebuilt.
    pub(super) request: Vec<u8>,
}

/// A reply value as text (empty for one that is none).
pub(super) fn text(v: &Value) -> String {
    match v {
        Value::BulkString(b) => String::from_utf8_lossy(b).into_owned(),
        Value::SimpleString(s) => s.clone(),
        Value::Int(i) => i.to_string(),
        _ => String::new(),
    }
}

/// `[id, [k, v, …]]` → a claimed job; `None` for a deleted entry (nil fields).
pub(super) fn parse_entry(v: &Value) -> Option<Claimed> {
    let Value::Array(parts) = v else { return None };
    let entry = text(parts.first()?);
    let Value::Array(kv) = parts.get(1)? else {
        return None;
    };
    let mut c = Claimed {
        entry,
        tenant: String::new(),
        id: String::new(),
        method: String::new(),
        gen: String::new(),
        request: Vec::new(),
    };
    for pair in kv.chunks(2) {
        let [k, v] = pair else { continue };
        match text(k).as_str() {
            "tenant" => c.tenant = text(v),
            "id" => c.id = text(v),
            "method" => c.method = text(v),
            "gen" => c.gen = text(v),
            "request" => {
                if let Value::BulkString(b) = v {
                    c.request = b.clone();
                }
            }
            _ => {}
        }
    }
    (!c.id.is_empty()).then_some(c)
}

/// Entries of an `XREADGROUP` reply: `[[stream, [entry, …]]]`.
pub(super) fn read_reply(v: &Value) -> Vec<Claimed> {
    let Value::Array(streams) = v else {
        return Vec::new();
    };
    streams
        .iter()
        .filter_map(|s| match s {
            Value::Array(p) => p.get(1),
            _ => None,
        })
        .flat_map(|entries| match entries {
            Value::Array(e) => e.iter().filter_map(parse_entry).collect(),
            _ => Vec::new(),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bulk(s: &str) -> Value {
        Value::BulkString(s.as_bytes().to_vec())
    }

    #[test]
    fn xreadgroup_replies_parse_into_jobs() {
        let entry = Value::Array(vec![
            bulk("1-0"),
            Value::Array(vec![
                bulk("tenant"),
                bulk("acme"),
                bulk("id"),
                bulk("ab12"),
                bulk("method"),
                bulk("tof_depth"),
                bulk("gen"),
                bulk("7"),
                bulk("request"),
                Value::BulkString(vec![0, 159, 1]),
            ]),
        ]);
        let reply = Value::Array(vec![Value::Array(vec![
            bulk("murk:queue"),
            Value::Array(vec![entry, Value::Array(vec![bulk("2-0"), Value::Nil])]),
        ])]);
        let jobs = read_reply(&reply);
        assert_eq!(jobs.len(), 1, "the deleted entry is skipped");
        let j = &jobs[0];
        assert_eq!(
            (
                j.entry.as_str(),
                j.tenant.as_str(),
                j.id.as_str(),
                j.gen.as_str()
            ),
            ("1-0", "acme", "ab12", "7")
        );
        assert_eq!(j.request, vec![0, 159, 1]);
        assert!(read_reply(&Value::Nil).is_empty());
    }
}
