//! The event channel: every replica subscribes, refreshes the views its callers watch when a
//! record changes, and stops the jobs it runs when a cancel is signalled. Missed events (while
//! the subscription was down) are made up for by refreshing every view on reconnection.

use std::sync::Arc;
use std::time::Duration;

use futures::StreamExt;

use super::shared::Shared;

pub(super) async fn listen(shared: Arc<Shared>) {
    let channel = shared.keys.channel();
    while !shared.is_stopping() {
        match shared.client.get_async_pubsub().await {
            Ok(mut pubsub) => {
                if let Err(e) = pubsub.subscribe(&channel).await {
                    tracing::warn!(error = %e, "redis: cannot subscribe to job events");
                } else {
                    refresh_all(&shared);
                    let mut messages = pubsub.on_message();
                    while let Some(msg) = messages.next().await {
                        handle(&shared, msg.get_payload_bytes());
                    }
                    tracing::warn!("redis: job event subscription ended; reconnecting");
                }
            }
            Err(e) => tracing::debug!(error = %e, "redis: job events unavailable"),
        }
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
}

fn handle(shared: &Arc<Shared>, payload: &[u8]) {
    let text = String::from_utf8_lossy(payload);
    let mut parts = text.splitn(3, '\t');
    let (Some(kind), Some(tenant), Some(id)) = (parts.next(), parts.next(), parts.next()) else {
        return;
    };
    if kind == "c" {
        // Stops the job if it runs here; a no-op elsewhere.
        shared.local.cancel(tenant, id);
    }
    if shared.is_watched(tenant, id) {
        let (s, tenant, id) = (shared.clone(), tenant.to_string(), id.to_string());
        tokio::spawn(async move { s.refresh(&tenant, &id).await });
    }
}

fn refresh_all(shared: &Arc<Shared>) {
    for (tenant, id) in shared.watched() {
        let s = shared.clone();
        tokio::spawn(async move { s.refresh(&tenant, &id).await });
    }
}
