//! The management HTTP API: a compatible subset of RabbitMQ's (`/api/...`,
//! JSON with RabbitMQ's field names), enough for `rabbitmqadmin` and
//! scripts written against RabbitMQ to list, declare, delete, publish,
//! get and purge, and to add users and grant permissions. Every request
//! needs HTTP basic auth with one of the broker's users, whose RabbitMQ
//! user tags decide what they may see and do (`caller`); bodies are capped
//! at [`MAX_BODY`].
//!
//! Definitions (`/api/definitions`) are `crate::definitions`' job. `/` is a
//! status page (`status.html`: plain HTML and a little JavaScript, no build
//! step) that reads the same API with the browser's basic-auth credentials.
//!
//! Layout, a file a resource as RabbitMQ's API has them: `overview`
//! (the overview, nodes, environment and the status page), `vhosts`,
//! `users` (and `whoami`), `permissions` (and topic permissions),
//! `exchanges` (and publishing), `queues` (and getting messages),
//! `bindings` (every listing of bindings), `connections`, `channels`,
//! `consumers`, `definitions`, `shovels`, `federation`, `parameters` (the
//! runtime-parameter listings), `policies` (and operator policies, the
//! cluster name, global parameters), `limits` (vhost and user limits),
//! `health` (the health checks and the aliveness test). Beside them:
//! `mod` (the router), `api` (the shared context and the errors),
//! `login` (basic auth and the caller's tags at the door), `common` (what every
//! resource's handlers share), `caller` (who calls and what their tags
//! let them do), `pagination` (RabbitMQ's `page`, `page_size`, `name`,
//! `sort`), `json` (objects and body parsing), `rates` (the sampler
//! behind `*_details`), `audit` (the log line of each change with the
//! acting user). A resource's file uses those and the broker; only
//! `bindings` uses two others' lookups (an exchange's, a queue's), and no
//! resource is used by those it uses.
//! Handlers reach the broker only
//! through [`Admin`](leveret_broker::Admin); they run on the listeners' thread.

mod api;
mod audit;
mod bindings;
mod caller;
mod channels;
mod common;
mod connections;
mod consumers;
mod definitions;
mod exchanges;
mod federation;
mod health;
pub mod json;
mod limits;
mod login;
mod overview;
mod pagination;
mod parameters;
mod permissions;
mod policies;
mod queues;
mod rates;
mod shovels;
mod users;
mod vhosts;

pub use api::Context;
use axum::extract::DefaultBodyLimit;
use axum::routing::{delete, get, post, put};
use axum::Router;
pub(crate) use caller::percent_decoded;
pub use rates::Rates;
use std::sync::Arc;

/// The largest request body read (a publish's payload, a definitions file).
pub const MAX_BODY: usize = 1024 * 1024;

/// The router of the management listener.
pub fn router(context: Context) -> Router {
    let context = Arc::new(context);
    let api = Router::new()
        .route("/", get(overview::status_page))
        .route("/api/overview", get(overview::overview))
        .route("/api/nodes", get(overview::nodes))
        .route("/api/nodes/{node}", get(overview::node))
        .route("/api/vhosts", get(vhosts::vhosts))
        .route(
            "/api/vhosts/{vhost}",
            get(vhosts::vhost)
                .put(vhosts::put_vhost)
                .delete(vhosts::delete_vhost),
        )
        .route("/api/vhost-limits", get(limits::vhost_limits))
        .route("/api/vhost-limits/{vhost}", get(limits::vhost_limits_of))
        .route(
            "/api/vhost-limits/{vhost}/{name}",
            put(limits::put_vhost_limit).delete(limits::delete_vhost_limit),
        )
        .route("/api/user-limits", get(limits::user_limits))
        .route("/api/user-limits/{user}", get(limits::user_limits_of))
        .route(
            "/api/user-limits/{user}/{name}",
            put(limits::put_user_limit).delete(limits::delete_user_limit),
        )
        .route("/api/users", get(users::users))
        .route(
            "/api/users/{name}",
            get(users::user)
                .put(users::put_user)
                .delete(users::delete_user),
        )
        .route("/api/whoami", get(users::whoami))
        .route("/api/environment", get(overview::environment))
        .route("/api/permissions", get(permissions::permissions))
        .route(
            "/api/permissions/{vhost}/{user}",
            get(permissions::permission)
                .put(permissions::put_permission)
                .delete(permissions::delete_permission),
        )
        .route(
            "/api/topic-permissions",
            get(permissions::topic_permissions),
        )
        .route(
            "/api/topic-permissions/{vhost}/{user}",
            put(permissions::put_topic_permission).delete(permissions::delete_topic_permission),
        )
        .route("/api/exchanges", get(exchanges::exchanges))
        .route("/api/exchanges/{vhost}", get(exchanges::exchanges_in))
        .route(
            "/api/exchanges/{vhost}/{name}",
            get(exchanges::exchange)
                .put(exchanges::put_exchange)
                .delete(exchanges::delete_exchange),
        )
        .route(
            "/api/exchanges/{vhost}/{name}/publish",
            post(exchanges::publish),
        )
        .route(
            "/api/exchanges/{vhost}/{name}/bindings/source",
            get(bindings::exchange_bindings_source),
        )
        .route(
            "/api/exchanges/{vhost}/{name}/bindings/destination",
            get(bindings::exchange_bindings_destination),
        )
        .route("/api/queues", get(queues::queues))
        .route("/api/queues/{vhost}", get(queues::queues_in))
        .route(
            "/api/queues/{vhost}/{name}",
            get(queues::queue)
                .put(queues::put_queue)
                .delete(queues::delete_queue),
        )
        .route("/api/queues/{vhost}/{name}/contents", delete(queues::purge))
        .route("/api/queues/{vhost}/{name}/get", post(queues::get_messages))
        .route(
            "/api/queues/{vhost}/{name}/bindings",
            get(bindings::queue_bindings),
        )
        .route("/api/bindings", get(bindings::bindings))
        .route("/api/bindings/{vhost}", get(bindings::bindings_in))
        .route(
            "/api/bindings/{vhost}/e/{source}/{kind}/{destination}",
            get(bindings::bindings_between).post(bindings::post_binding),
        )
        .route(
            "/api/bindings/{vhost}/e/{source}/{kind}/{destination}/{props}",
            get(bindings::binding).delete(bindings::delete_binding),
        )
        .route("/api/connections", get(connections::connections))
        .route(
            "/api/connections/{name}",
            get(connections::connection).delete(connections::close_connection),
        )
        .route("/api/channels", get(channels::channels))
        .route("/api/consumers", get(consumers::consumers))
        .route("/api/consumers/{vhost}", get(consumers::consumers_in))
        .route(
            "/api/definitions",
            get(definitions::definitions).post(definitions::import_definitions),
        )
        .route(
            "/api/definitions/{vhost}",
            get(definitions::vhost_definitions).post(definitions::import_vhost_definitions),
        )
        .route("/api/aliveness-test/{vhost}", get(health::aliveness_test))
        .route("/api/shovels", get(shovels::shovels))
        .route("/api/shovels/{vhost}", get(shovels::shovels_in))
        .route(
            "/api/parameters/shovel/{vhost}/{name}",
            get(shovels::shovel_parameter)
                .put(shovels::put_shovel)
                .delete(shovels::delete_shovel),
        )
        .route("/api/parameters", get(parameters::all))
        .route("/api/parameters/{component}", get(parameters::of_component))
        .route(
            "/api/parameters/{component}/{vhost}",
            get(parameters::of_component_in),
        )
        .route(
            "/api/parameters/federation-upstream/{vhost}/{name}",
            get(federation::upstream)
                .put(federation::put_upstream)
                .delete(federation::delete_upstream),
        )
        .route("/api/policies", get(policies::all))
        .route("/api/policies/{vhost}", get(policies::in_vhost))
        .route(
            "/api/policies/{vhost}/{name}",
            get(policies::get_one)
                .put(policies::put_one)
                .delete(policies::delete_one),
        )
        .route("/api/operator-policies", get(policies::operator_all))
        .route(
            "/api/operator-policies/{vhost}",
            get(policies::operator_in_vhost),
        )
        .route(
            "/api/operator-policies/{vhost}/{name}",
            get(policies::operator_get_one)
                .put(policies::operator_put_one)
                .delete(policies::operator_delete_one),
        )
        .route(
            "/api/cluster-name",
            get(policies::cluster_name).put(policies::put_cluster_name),
        )
        .route("/api/global-parameters", get(policies::global_parameters))
        .route(
            "/api/global-parameters/{name}",
            get(policies::global_parameter)
                .put(policies::put_global_parameter)
                .delete(policies::delete_global_parameter),
        )
        .route("/api/federation-links", get(federation::links))
        .route("/api/federation-links/{vhost}", get(federation::links_in))
        .route("/api/health/checks/alarms", get(health::alarms))
        .route("/api/health/checks/local-alarms", get(health::local_alarms))
        .route(
            "/api/health/checks/port-listener/{port}",
            get(health::port_listener),
        )
        .route(
            "/api/health/checks/protocol-listener/{protocol}",
            get(health::protocol_listener),
        )
        .route(
            "/api/health/checks/virtual-hosts",
            get(health::virtual_hosts),
        )
        .route(
            "/api/health/checks/node-is-quorum-critical",
            get(health::node_is_quorum_critical),
        )
        .route(
            "/api/health/checks/node-is-mirror-sync-critical",
            get(health::node_is_mirror_sync_critical),
        )
        .route(
            "/api/health/checks/certificate-expiration/{within}/{unit}",
            get(health::certificate_expiration),
        )
        .fallback(common::unknown)
        .route_layer(axum::middleware::from_fn(audit::log_changes))
        .route_layer(axum::middleware::from_fn_with_state(
            Arc::clone(&context),
            login::authenticate,
        ));
    api.layer(DefaultBodyLimit::max(MAX_BODY))
        .with_state(context)
}
