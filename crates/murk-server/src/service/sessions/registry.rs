//! The sessions open on this replica, bounded per replica and per tenant.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Session limits (`murk serve --max-sessions`, `--max-sessions-per-tenant`,
/// `--session-config-timeout`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SessionLimits {
    /// Sessions open at once on this replica.
    pub max_sessions: usize,
    /// Sessions open at once for one tenant on this replica.
    pub max_sessions_per_tenant: usize,
    /// How long a new stream may take to send its configuration.
    pub config_timeout: Duration,
}

impl Default for SessionLimits {
    fn default() -> Self {
        Self {
            max_sessions: 32,
            max_sessions_per_tenant: 8,
            config_timeout: Duration::from_secs(10),
        }
    }
}

/// Why a session was refused.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// The replica has `max_sessions` open.
    Replica(usize),
    /// The tenant has `max_sessions_per_tenant` open.
    Tenant(usize),
}

#[derive(Debug, Default)]
struct Open {
    total: usize,
    by_tenant: HashMap<String, usize>,
}

/// Open sessions by tenant. Cheap to clone.
#[derive(Clone, Debug)]
pub struct SessionRegistry {
    limits: SessionLimits,
    open: Arc<Mutex<Open>>,
}

/// A session's place in the registry, given back when dropped.
#[derive(Debug)]
pub struct SessionSlot {
    tenant: String,
    open: Arc<Mutex<Open>>,
}

impl SessionRegistry {
    /// An empty registry.
    pub fn new(limits: SessionLimits) -> Self {
        Self {
            limits,
            open: Arc::default(),
        }
    }

    /// The limits in force.
    pub fn limits(&self) -> SessionLimits {
        self.limits
    }

    /// Sessions open now.
    pub fn open_sessions(&self) -> usize {
        self.open.lock().unwrap_or_else(|p| p.into_inner()).total
    }

    /// A slot for `tenant`, or why not.
    pub fn open(&self, tenant: &str) -> Result<SessionSlot, Refusal> {
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        if open.total >= self.limits.max_sessions {
            return Err(Refusal::Replica(self.limits.max_sessions));
        }
        let mine = open.by_tenant.entry(tenant.to_string()).or_default();
        if *mine >= self.limits.max_sessions_per_tenant {
            return Err(Refusal::Tenant(self.limits.max_sessions_per_tenant));
        }
        *mine += 1;
        open.total += 1;
        Ok(SessionSlot {
            tenant: tenant.to_string(),
            open: self.open.clone(),
        })
    }
}

impl Drop for SessionSlot {
    fn drop(&mut self) {
        let mut open = self.open.lock().unwrap_or_else(|p| p.into_inner());
        open.total = open.total.saturating_sub(1);
        if let Some(n) = open.by_tenant.get_mut(&self.tenant) {
            *n -= 1;
            if *n == 0 {
                open.by_tenant.remove(&self.tenant);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounds_per_replica_and_per_tenant_and_frees_on_drop() {
        let r = SessionRegistry::new(SessionLimits {
            max_sessions: 3,
            max_sessions_per_tenant: 2,
            ..SessionLimits::default()
        });
        let a1 = r.open("a").unwrap();
        let _a2 = r.open("a").unwrap();
        assert_eq!(r.open("a").unwrap_err(), Refusal::Tenant(2));
        let _b1 = r.open("b").unwrap();
        assert_eq!(r.open("c").unwrap_err(), Refusal::Replica(3));
        drop(a1);
        assert_eq!(r.open_sessions(), 2);
        let _a3 = r.open("a").unwrap();
        assert_eq!(r.open("b").unwrap_err(), Refusal::Replica(3));
    }
}
