//! `/api/users[/{name}]` and `/api/whoami`: listing users with their
//! password hashes and tags as RabbitMQ shows them, adding or changing one
//! (a password hashed here, off the listeners' thread, or a RabbitMQ
//! hash), deleting one with their permissions. Uses `common`, `json`,
//! `caller` and the broker through `Admin`.

use super::api::ApiError;
use super::caller::Caller;
use super::common::{body_object, created_or_not, no_content, ApiResult, Ctx};
use super::json;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::{Extension, Json};
use leveret_broker::{PasswordHash, User, RABBIT_SHA256};
use serde_json::{json, Value};

pub async fn users(State(c): Ctx) -> Json<Value> {
    let users = c.admin.users();
    Json(Value::Array(
        users
            .iter()
            .map(|(name, user)| user_json(name, user))
            .collect(),
    ))
}

/// A user as RabbitMQ's `/api/users` shows one.
fn user_json(name: &str, user: &User) -> Value {
    let (password_hash, hashing_algorithm) = user.password_hash.to_rabbitmq();
    json!({
        "name": name,
        "password_hash": password_hash,
        "hashing_algorithm": hashing_algorithm,
        "tags": user.tags,
        "limits": {},
    })
}

pub async fn user(State(c): Ctx, Path(name): Path<String>) -> ApiResult<Json<Value>> {
    let user = c
        .admin
        .user(&name)
        .ok_or_else(|| ApiError::not_found(format!("no user '{name}'")))?;
    Ok(Json(user_json(&name, &user)))
}

/// RabbitMQ's `PUT /api/users/{name}`: `password` (hashed here) or
/// `password_hash` with `hashing_algorithm`, and `tags` (a list or a
/// comma-separated string). A new user needs a password; an existing one
/// without either keeps theirs. 201 for a new user, 204 for a change.
pub async fn put_user(State(c): Ctx, Path(name): Path<String>, body: Bytes) -> ApiResult {
    let body = body_object(&body)?;
    let field = |key: &str| json::text(&body, key, "").map_err(ApiError::bad_request);
    let existing = c.admin.user(&name);
    let password = field("password")?;
    let password_hash = field("password_hash")?;
    let hash = if !password.is_empty() {
        // argon2id takes tens of milliseconds: off the listeners' thread.
        let password = password.to_owned();
        tokio::task::spawn_blocking(move || PasswordHash::new(&password))
            .await
            .map_err(|_| ApiError::bad_request("the password could not be hashed"))?
    } else if body.contains_key("password_hash") {
        let algorithm =
            json::text(&body, "hashing_algorithm", RABBIT_SHA256).map_err(ApiError::bad_request)?;
        PasswordHash::from_rabbitmq(password_hash, algorithm).ok_or_else(|| {
            ApiError::bad_request(format!(
                "password_hash is not a {algorithm} hash Leveret can check"
            ))
        })?
    } else {
        existing
            .as_ref()
            .map(|user| user.password_hash.clone())
            .ok_or_else(|| {
                ApiError::bad_request("a new user needs a password or a password_hash")
            })?
    };
    let tags = json::user_tags(body.get("tags"));
    let created = c
        .admin
        .put_user(
            &name,
            User {
                password_hash: hash,
                tags,
            },
        )
        .await?;
    Ok(created_or_not(created))
}

/// RabbitMQ's `DELETE /api/users/{name}`: the user and their permissions.
pub async fn delete_user(State(c): Ctx, Path(name): Path<String>) -> ApiResult {
    if c.admin.delete_user(&name).await? {
        Ok(no_content())
    } else {
        Err(ApiError::not_found(format!("no user '{name}'")))
    }
}

pub async fn whoami(State(c): Ctx, Extension(caller): Extension<Caller>) -> Json<Value> {
    let tags = c.admin.user(&caller.user).map(|user| user.tags);
    Json(json!({ "name": caller.user, "tags": tags.unwrap_or_default() }))
}
