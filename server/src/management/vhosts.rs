//! `/api/vhosts[/{vhost}]`: listing vhosts (with their message totals),
//! reading one, creating one (its creator is granted everything on it),
//! and deleting one with everything in it (RabbitMQ's 204, or 404 when
//! there is no such vhost): its shovels and federation upstreams are
//! stopped and forgotten first (`crate::uplink`, `crate::federation`:
//! with no upstream left, no federation link of the vhost is wanted),
//! then the broker deletes the rest, its policies included, through
//! [`leveret_broker::Admin::delete_vhost`]. Uses `common`, `caller` and
//! the broker through `Admin`.

use super::api::{ApiError, Context};
use super::caller::Caller;
use super::common::{created_or_not, listing, no_content, require_vhost, ApiResult, Ctx, Params};
use axum::extract::{Path, Query, State};
use axum::{Extension, Json};
use leveret_broker::Permission;
use serde_json::{json, Value};

fn vhost_json(c: &Context, name: &str) -> Value {
    let (mut ready, mut unacked) = (0, 0);
    for q in c.admin.queue_refs().iter().filter(|q| q.vhost() == name) {
        let info = q.info();
        ready += info.messages_ready;
        unacked += info.messages_unacknowledged;
    }
    json!({
        "name": name,
        "description": "",
        "tags": [],
        "metadata": {"description": "", "tags": []},
        "default_queue_type": "classic",
        "tracing": false,
        "messages": ready + unacked,
        "messages_ready": ready,
        "messages_unacknowledged": unacked,
        "cluster_state": { c.node.as_str(): "running" },
    })
}
pub async fn vhosts(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Query(query): Params,
) -> ApiResult<Json<Value>> {
    let names = c.admin.vhosts();
    let objects = names
        .iter()
        .filter(|n| caller.sees_vhost(n))
        .map(|n| vhost_json(&c, n))
        .collect();
    listing(objects, &query).await
}
pub async fn vhost(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(Json(vhost_json(&c, &vhost)))
}
/// Creates a vhost (201), or leaves an existing one be (204); it lasts
/// across restarts. As in RabbitMQ (since 3.7), the user who creates it
/// is granted everything on it.
pub async fn put_vhost(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult {
    let created = c.admin.add_vhost(&vhost).await?;
    if created {
        c.admin
            .set_permission(&caller.user, &vhost, Permission::full())
            .await?;
    }
    Ok(created_or_not(created))
}

/// Deletes a vhost and everything in it, its shovels and federation
/// upstreams first.
pub async fn delete_vhost(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult {
    require_vhost(&c, &vhost)?;
    for shovel in c.links.shovels.list() {
        if shovel.vhost == vhost {
            c.links.shovels.delete(&vhost, &shovel.name).await?;
        }
    }
    let federation = &c.links.federation;
    for (in_vhost, name, _) in federation.upstreams() {
        if in_vhost == vhost {
            federation.delete_upstream(&vhost, &name).await?;
        }
    }
    if c.admin.delete_vhost(&vhost).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!("no vhost '{vhost}'")))
    }
}
