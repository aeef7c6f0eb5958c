//! `DELETE /api/vhosts/{vhost}`: deletes a vhost and everything in it
//! (RabbitMQ's 204, or 404 when there is no such vhost). Its shovels and
//! federation upstreams are stopped and forgotten first (`crate::uplink`,
//! `crate::federation`: with no upstream left, no federation link of the
//! vhost is wanted), then the broker deletes the rest, its policies
//! included, through [`leveret_broker::Admin::delete_vhost`].

use super::handlers::{no_content, require_vhost, ApiResult, Ctx};
use super::ApiError;
use axum::extract::{Path, State};

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
