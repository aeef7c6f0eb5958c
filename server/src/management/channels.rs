//! `/api/channels`: the channels the caller may see, paginated when
//! asked. Uses `common`, `json`, `caller` and the broker through `Admin`.

use super::caller::Caller;
use super::common::{listing, ApiResult, Ctx, Params};
use super::json;
use axum::extract::{Query, State};
use axum::{Extension, Json};
use serde_json::Value;

pub async fn channels(
    State(c): Ctx,
    Extension(caller): Extension<Caller>,
    Query(query): Params,
) -> ApiResult<Json<Value>> {
    let objects = c
        .admin
        .channels()
        .iter()
        .filter(|ch| caller.sees_user(&ch.user))
        .map(|ch| json::channel(ch, &c.node))
        .collect();
    listing(objects, &query).await
}
