//! Who is calling the management API and what they may see and do, by
//! RabbitMQ's user tags: `administrator` may do everything; `monitoring`
//! may read everything and change what `management` may; `management` and
//! `policymaker` see and change only the vhosts they have a permission on,
//! and only their own connections. A user without any of these tags cannot
//! log in to the API (401 `Not management user`); users, permissions,
//! definitions, vhost changes, closing connections, shovels
//! (parameters), operator policies and setting the cluster name are the
//! administrator's (401 `Not administrator user`); policies need the
//! `policymaker` tag (401 `Not policymaker user`). Uses the broker's
//! users and permissions through `Admin`. The tags only open the door:
//! each operation on an object is then checked against the caller's
//! permissions by the broker (`Admin::as_user`), as AMQP checks it.

use super::api::ApiError;
use axum::http::Method;
use leveret_broker::Admin;
use std::collections::HashSet;

/// What a caller's tags let them do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// `administrator`.
    Administrator,
    /// `monitoring`.
    Monitoring,
    /// `management` or `policymaker`.
    Management,
}

impl Role {
    /// The role `tags` give, if any lets the user into the API.
    pub fn of(tags: &[String]) -> Option<Role> {
        let has = |tag: &str| tags.iter().any(|t| t == tag);
        if has("administrator") {
            Some(Role::Administrator)
        } else if has("monitoring") {
            Some(Role::Monitoring)
        } else if has("management") || has("policymaker") {
            Some(Role::Management)
        } else {
            None
        }
    }
}

/// `/api/...` as percent-decoded segments (`/api/queues/%2F/q` is
/// `["queues", "/", "q"]`); `None` for paths outside the API.
pub fn api_segments(path: &str) -> Option<Vec<String>> {
    let rest = path.strip_prefix("/api/")?;
    Some(rest.split('/').map(percent_decoded).collect())
}

pub(crate) fn percent_decoded(segment: &str) -> String {
    let bytes = segment.as_bytes();
    let mut out = Vec::with_capacity(bytes.len());
    let mut i = 0;
    while i < bytes.len() {
        let hex = |b: u8| (b as char).to_digit(16);
        match (
            bytes[i],
            bytes.get(i + 1).copied().and_then(hex),
            bytes.get(i + 2).copied().and_then(hex),
        ) {
            (b'%', Some(high), Some(low)) => {
                out.push((high * 16 + low) as u8);
                i += 3;
            }
            (b, _, _) => {
                out.push(b);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// The authenticated caller of a request (a request extension).
#[derive(Debug, Clone)]
pub struct Caller {
    /// The user name.
    pub user: String,
    /// What their tags allow.
    pub role: Role,
    /// The vhosts they have a permission on.
    vhosts: HashSet<String>,
    /// Tagged `policymaker` (or `administrator`): may see and change the
    /// policies of those vhosts.
    policymaker: bool,
}

impl Caller {
    /// The caller `user`, by their tags; 401 when no tag lets them in.
    pub fn new(user: &str, admin: &Admin) -> Result<Caller, ApiError> {
        let tags = admin.user(user).map(|user| user.tags).unwrap_or_default();
        let role =
            Role::of(&tags).ok_or_else(|| ApiError::not_authorised("Not management user"))?;
        let vhosts = admin
            .permissions()
            .into_iter()
            .filter(|(u, ..)| u == user)
            .map(|(_, vhost, _)| vhost)
            .collect();
        Ok(Caller {
            user: user.to_owned(),
            role,
            vhosts,
            policymaker: tags.iter().any(|t| t == "policymaker"),
        })
    }

    /// Whether listings show `vhost`'s objects to the caller.
    pub fn sees_vhost(&self, vhost: &str) -> bool {
        self.role != Role::Management || self.vhosts.contains(vhost)
    }

    /// Whether listings show a connection (or channel) of `user`.
    pub fn sees_user(&self, user: &str) -> bool {
        self.role != Role::Management || self.user == user
    }

    /// Checks a request against the caller's role: `segments` is the path
    /// after `/api/`, percent-decoded.
    pub fn authorize(&self, method: &Method, segments: &[String]) -> Result<(), ApiError> {
        if self.role == Role::Administrator {
            return Ok(());
        }
        let reads = method == Method::GET || method == Method::HEAD;
        let first = segments.first().map(String::as_str).unwrap_or("");
        if first == "policies" && !self.policymaker {
            return Err(ApiError::not_authorised("Not policymaker user"));
        }
        let admin_only = matches!(
            first,
            "users"
                | "permissions"
                | "topic-permissions"
                | "definitions"
                | "operator-policies"
                | "user-limits"
                | "environment"
                | "global-parameters"
        ) || (matches!(
            first,
            "vhosts" | "connections" | "parameters" | "cluster-name" | "vhost-limits"
        ) && !reads);
        if admin_only {
            return Err(ApiError::not_authorised("Not administrator user"));
        }
        let scoped = matches!(
            first,
            "exchanges"
                | "queues"
                | "bindings"
                | "consumers"
                | "aliveness-test"
                | "vhosts"
                | "vhost-limits"
                | "shovels"
                | "policies"
                | "federation-links"
        );
        match segments.get(1) {
            Some(vhost) if scoped => {
                let may_read_all = self.role == Role::Monitoring && reads;
                if may_read_all || self.vhosts.contains(vhost) {
                    Ok(())
                } else {
                    Err(ApiError::not_authorised(
                        "User not authorised to access virtual host",
                    ))
                }
            }
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn caller(role: Role, vhosts: &[&str]) -> Caller {
        Caller {
            user: "u".into(),
            role,
            vhosts: vhosts.iter().map(|v| v.to_string()).collect(),
            policymaker: false,
        }
    }

    #[test]
    fn policies_are_the_policymakers_and_operator_policies_the_administrators() {
        let get = Method::GET;
        let put = Method::PUT;
        let manager = caller(Role::Management, &["cell"]);
        assert!(manager.authorize(&get, &path("policies/cell")).is_err());
        let policymaker = Caller {
            policymaker: true,
            ..caller(Role::Management, &["cell"])
        };
        assert!(policymaker
            .authorize(&put, &path("policies/cell/p"))
            .is_ok());
        assert!(policymaker
            .authorize(&get, &path("policies/other"))
            .is_err());
        assert!(policymaker
            .authorize(&put, &path("operator-policies/cell/p"))
            .is_err());
        assert!(policymaker.authorize(&get, &path("cluster-name")).is_ok());
        assert!(policymaker.authorize(&put, &path("cluster-name")).is_err());
        // Global parameters (the MQTT vhost mappings) are administrators'.
        assert!(policymaker
            .authorize(&get, &path("global-parameters"))
            .is_err());
        assert!(policymaker
            .authorize(&put, &path("global-parameters/mqtt_default_vhosts"))
            .is_err());
        let administrator = caller(Role::Administrator, &[]);
        assert!(administrator
            .authorize(&put, &path("global-parameters/mqtt_default_vhosts"))
            .is_ok());
        assert!(administrator
            .authorize(&put, &path("operator-policies/cell/p"))
            .is_ok());
    }

    fn path(p: &str) -> Vec<String> {
        p.split('/').map(str::to_owned).collect()
    }

    #[test]
    fn api_paths_are_split_and_decoded() {
        assert_eq!(
            api_segments("/api/queues/%2F/a%20b"),
            Some(vec!["queues".to_owned(), "/".to_owned(), "a b".to_owned()])
        );
        assert_eq!(api_segments("/"), None);
        assert_eq!(
            api_segments("/api/x/%zz%4"),
            Some(vec!["x".to_owned(), "%zz%4".to_owned()])
        );
    }

    #[test]
    fn rabbitmqs_tags_decide_what_a_caller_may_do() {
        assert_eq!(Role::of(&[]), None);
        assert_eq!(Role::of(&["impersonator".into()]), None);
        assert_eq!(
            Role::of(&["management".into(), "monitoring".into()]),
            Some(Role::Monitoring)
        );
        let admin = caller(Role::Administrator, &[]);
        let monitor = caller(Role::Monitoring, &["/"]);
        let manager = caller(Role::Management, &["robots"]);
        for who in [&admin, &monitor, &manager] {
            assert!(who.authorize(&Method::GET, &path("overview")).is_ok());
        }
        assert!(admin.authorize(&Method::PUT, &path("vhosts/new")).is_ok());
        for who in [&monitor, &manager] {
            for (method, p) in [
                (Method::GET, "users"),
                (Method::PUT, "permissions/robots/u"),
                (Method::GET, "definitions"),
                (Method::PUT, "vhosts/new"),
                (Method::DELETE, "connections/c1"),
            ] {
                let refused = who.authorize(&method, &path(p)).unwrap_err();
                assert_eq!(refused.reason, "Not administrator user", "{p}");
            }
        }
        assert!(monitor
            .authorize(&Method::GET, &path("queues/robots"))
            .is_ok());
        assert!(monitor
            .authorize(&Method::PUT, &path("queues/robots/q"))
            .is_err());
        assert!(manager
            .authorize(&Method::PUT, &path("queues/robots/q"))
            .is_ok());
        assert!(manager
            .authorize(&Method::GET, &path("queues/other"))
            .is_err());
        assert!(manager.sees_vhost("robots") && !manager.sees_vhost("/"));
        assert!(monitor.sees_vhost("anything") && monitor.sees_user("someone"));
        assert!(manager.sees_user("u") && !manager.sees_user("someone"));
    }
}
