//! `DELETE /api/vhosts/{vhost}`: deletes a vhost and everything in it
//! (RabbitMQ's 204, or 404 when there is no such vhost), through
//! [`leveret_broker::Admin::delete_vhost`].

use super::handlers::{no_content, ApiResult, Ctx};
use super::ApiError;
use axum::extract::{Path, State};

pub async fn delete_vhost(State(c): Ctx, Path(vhost): Path<String>) -> ApiResult {
    if c.admin.delete_vhost(&vhost).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!("no vhost '{vhost}'")))
    }
}
