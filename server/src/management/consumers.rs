//! `/api/consumers[/{vhost}]`: the consumers in the vhosts the caller
//! may see, each with its connection's peer. Uses `common`, `json`,
//! `caller` and the broker through `Admin`.

use super::api::Context;
use super::caller::Caller;
use super::common::{require_vhost, ApiResult, Ctx};
use super::json;
use axum::extract::{Path, State};
use axum::{Extension, Json};
use serde_json::Value;
use std::collections::HashMap;

fn consumer_list(c: &Context, caller: &Caller, vhost: Option<&str>) -> Json<Value> {
    let peers: HashMap<u64, String> = c
        .admin
        .connections()
        .into_iter()
        .map(|conn| (conn.id, conn.peer))
        .collect();
    Json(Value::Array(
        c.admin
            .consumers()
            .iter()
            .filter(|consumer| vhost.is_none_or(|v| consumer.vhost == v))
            .filter(|consumer| caller.sees_vhost(&consumer.vhost))
            .map(|consumer| {
                let peer = peers
                    .get(&consumer.connection_id)
                    .map_or("", String::as_str);
                json::consumer(consumer, peer, &c.node)
            })
            .collect(),
    ))
}

pub async fn consumers(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    consumer_list(&c, &caller, None)
}

pub async fn consumers_in(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Path(vhost): Path<String>,
) -> ApiResult<Json<Value>> {
    require_vhost(&c, &vhost)?;
    Ok(consumer_list(&c, &caller, Some(&vhost)))
}
