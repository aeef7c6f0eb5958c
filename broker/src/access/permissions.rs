//! Who may do what: RabbitMQ's permissions. Each (user, vhost) pair may
//! have a [`Permission`] (configure, write and read patterns over resource
//! names) and, per topic exchange, a [`TopicPermission`] (write and read
//! patterns over routing keys). A user without a permission on a vhost
//! cannot open it.
//!
//! Matching is RabbitMQ's: a pattern matches when it matches anywhere in
//! the name (anchor it with `^` and `$`), the empty pattern means `^$`,
//! the default exchange is checked under the name `amq.default`, and a
//! topic permission's `{username}` and `{vhost}` are replaced by the
//! connection's (escaped, so a name's dots match only dots). A topic
//! exchange without a topic permission for the user is open to them.
//!
//! `.*`, the empty pattern and a literal name or name prefix (`^name$`,
//! `^name`) are matched as strings. Other patterns are compiled with the
//! `regex` crate, whose matching takes time linear in the name whatever
//! the pattern (no backtracking), each compiled program capped at
//! [`PATTERN_SIZE_LIMIT`] bytes. PCRE features it lacks (look-around,
//! back-references) are refused when the pattern is set, never at a
//! check; so is every other pattern in a build without the `regex`
//! feature.
//!
//! Channels hold a [`VhostAccess`] and re-read it only when
//! [`Permissions::generation`] moves, so a check costs one atomic load and
//! one match (none for `.*`), and a change applies to the next operation
//! of every open channel. Uses `error` and nothing else of the broker.

use crate::error::{AmqpError, AmqpResult};
use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, RwLock};

/// The largest compiled program a pattern may take, in bytes.
pub const PATTERN_SIZE_LIMIT: usize = 1 << 20;

/// A user's patterns on a vhost, as RabbitMQ's `set_permissions` takes
/// them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Permission {
    /// Resources the user may declare and delete.
    pub configure: String,
    /// Resources the user may publish to and bind to.
    pub write: String,
    /// Resources the user may consume from, get from, purge and bind from.
    pub read: String,
}

impl Permission {
    /// Whether the regex engine can run all three patterns.
    pub fn check(&self) -> Result<(), PatternError> {
        for pattern in [&self.configure, &self.write, &self.read] {
            Matcher::compile(pattern, None)?;
        }
        Ok(())
    }

    /// `.*` for all three: everything in the vhost.
    pub fn full() -> Self {
        Permission {
            configure: ".*".into(),
            write: ".*".into(),
            read: ".*".into(),
        }
    }
}

/// A user's routing-key patterns on one topic exchange of a vhost, as
/// RabbitMQ's `set_topic_permissions` takes them.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicPermission {
    /// Routing keys the user may publish with.
    pub write: String,
    /// Routing keys the user may bind with.
    pub read: String,
}

impl TopicPermission {
    /// Whether the regex engine can run both patterns for `user` in
    /// `vhost`: checked as they will run, with the names put in (a long
    /// name repeated in a pattern can pass with placeholders and still
    /// exceed the size limit).
    pub fn check(&self, user: &str, vhost: &str) -> Result<(), PatternError> {
        for pattern in [&self.write, &self.read] {
            Matcher::compile(pattern, Some((user, vhost)))?;
        }
        Ok(())
    }
}

/// A pattern that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("permission pattern '{pattern}': {reason}")]
pub struct PatternError {
    /// The pattern as given.
    pub pattern: String,
    /// Why it was refused.
    pub reason: String,
}

/// The three rights of RabbitMQ's model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Right {
    /// Declare, delete.
    Configure,
    /// Publish to, be bound to.
    Write,
    /// Consume, get, purge, be bound from.
    Read,
}

/// What a right is checked on.
#[derive(Debug, Clone, Copy)]
pub enum Resource<'a> {
    /// A queue, by name.
    Queue(&'a str),
    /// An exchange, by name (`""` is the default exchange).
    Exchange(&'a str),
}

/// A compiled pattern (also a policy's, in a build without the `regex`
/// feature).
#[derive(Debug, Clone)]
pub(crate) enum Matcher {
    /// `.*`: every name.
    Everything,
    /// `^name$` with a literal name (and the empty pattern, which means
    /// `^$`): that name only.
    Exactly(String),
    /// `^name` or `^name.*` with a literal name: the names beginning with it.
    Prefix(String),
    #[cfg(feature = "regex")]
    Regex(regex::Regex),
}

impl Matcher {
    /// Compiles `pattern` with `{username}` and `{vhost}` replaced when
    /// `variables` is given (topic permissions).
    pub(crate) fn compile(
        pattern: &str,
        variables: Option<(&str, &str)>,
    ) -> Result<Matcher, PatternError> {
        if pattern == ".*" {
            return Ok(Matcher::Everything);
        }
        if let Some(literal) = Matcher::literal(pattern, variables) {
            return Ok(literal);
        }
        #[cfg(feature = "regex")]
        {
            let source = match variables {
                Some((user, vhost)) => pattern
                    .replace("{username}", &regex::escape(user))
                    .replace("{vhost}", &regex::escape(vhost)),
                None => pattern.to_owned(),
            };
            regex::RegexBuilder::new(&source)
                .size_limit(PATTERN_SIZE_LIMIT)
                .build()
                .map(Matcher::Regex)
                .map_err(|e| PatternError {
                    pattern: pattern.to_owned(),
                    reason: e.to_string(),
                })
        }
        #[cfg(not(feature = "regex"))]
        Err(PatternError {
            pattern: pattern.to_owned(),
            reason: "this broker was built without a regular expression engine \
                     (leveret-broker's `regex` feature): only `.*`, the empty pattern, \
                     `^name$`, `^name` and `^name.*` with a literal name are understood"
                .to_owned(),
        })
    }

    /// The pattern as a name or a name's beginning, if it is one: `^`, then
    /// characters that are not regex syntax (or are escaped with `\`) and
    /// placeholders, then `$`, `.*` or nothing. Such patterns match the
    /// same names as the regex engine would, without it.
    fn literal(pattern: &str, variables: Option<(&str, &str)>) -> Option<Matcher> {
        if pattern.is_empty() {
            return Some(Matcher::Exactly(String::new()));
        }
        let body = pattern.strip_prefix('^')?;
        let (mut rest, exact) = match (body.strip_suffix('$'), body.strip_suffix(".*")) {
            (Some(name), _) => (name, true),
            (None, Some(name)) => (name, false),
            (None, None) => (body, false),
        };
        let mut name = String::with_capacity(rest.len());
        while let Some(c) = rest.chars().next() {
            if let Some((user, vhost)) = variables {
                let placeholders = [("{username}", user), ("{vhost}", vhost)];
                if let Some((after, value)) = placeholders
                    .iter()
                    .find_map(|(key, value)| Some((rest.strip_prefix(key)?, value)))
                {
                    name.push_str(value);
                    rest = after;
                    continue;
                }
            }
            rest = &rest[c.len_utf8()..];
            match c {
                '\\' => {
                    let escaped = rest.chars().next().filter(char::is_ascii_punctuation)?;
                    name.push(escaped);
                    rest = &rest[1..];
                }
                '.' | '+' | '*' | '?' | '(' | ')' | '|' | '[' | ']' | '{' | '}' | '^' | '$' => {
                    return None
                }
                c => name.push(c),
            }
        }
        Some(if exact {
            Matcher::Exactly(name)
        } else {
            Matcher::Prefix(name)
        })
    }

    pub(crate) fn matches(&self, name: &str) -> bool {
        match self {
            Matcher::Everything => true,
            Matcher::Exactly(exact) => name == exact,
            Matcher::Prefix(prefix) => name.starts_with(prefix.as_str()),
            #[cfg(feature = "regex")]
            Matcher::Regex(regex) => regex.is_match(name),
        }
    }
}

/// Checks that `pattern` can be used as a permission pattern.
pub fn check_pattern(pattern: &str) -> Result<(), PatternError> {
    Matcher::compile(pattern, Some(("user", "vhost"))).map(drop)
}

#[derive(Debug, Clone)]
struct CompiledTopic {
    write: Matcher,
    read: Matcher,
}

/// One user's rights in one vhost, compiled: what a channel checks.
#[derive(Debug)]
pub struct VhostAccess {
    user: String,
    vhost: String,
    configure: Matcher,
    write: Matcher,
    read: Matcher,
    topics: HashMap<String, CompiledTopic>,
}

impl VhostAccess {
    /// Checks `right` on `resource`: 403 ACCESS_REFUSED with RabbitMQ's
    /// text when refused.
    pub fn check(&self, right: Right, resource: Resource<'_>) -> AmqpResult<()> {
        let matcher = match right {
            Right::Configure => &self.configure,
            Right::Write => &self.write,
            Right::Read => &self.read,
        };
        let (kind, name) = match resource {
            Resource::Queue(name) => ("queue", name),
            Resource::Exchange("") => ("exchange", "amq.default"),
            Resource::Exchange(name) => ("exchange", name),
        };
        if matcher.matches(name) {
            return Ok(());
        }
        Err(AmqpError::access_refused(format_args!(
            "access to {kind} '{name}' in vhost '{}' refused for user '{}'",
            self.vhost, self.user
        )))
    }

    /// Checks a routing key against the user's topic permission on a topic
    /// `exchange` (`Write` for publishing, `Read` for binding); an exchange
    /// without one is open.
    pub fn check_topic(&self, right: Right, exchange: &str, routing_key: &str) -> AmqpResult<()> {
        let Some(topic) = self.topics.get(exchange) else {
            return Ok(());
        };
        let allowed = match right {
            Right::Write => topic.write.matches(routing_key),
            Right::Read => topic.read.matches(routing_key),
            Right::Configure => true,
        };
        if allowed {
            return Ok(());
        }
        Err(AmqpError::access_refused(format_args!(
            "access to topic '{routing_key}' in exchange '{exchange}' in vhost '{}' refused for user '{}'",
            self.vhost, self.user
        )))
    }

    /// Whether the user has a topic permission on any exchange (so
    /// publishing must look at the exchange's type).
    pub fn has_topic_permissions(&self) -> bool {
        !self.topics.is_empty()
    }

    /// RabbitMQ's checks for declaring (not passively) the queue `queue`:
    /// configure on it, and when it is being created with a dead-letter
    /// exchange, read on the queue and write on that exchange.
    pub fn check_queue_declare(
        &self,
        queue: &str,
        created_with_dead_letter_exchange: Option<&str>,
    ) -> AmqpResult<()> {
        self.check(Right::Configure, Resource::Queue(queue))?;
        if let Some(exchange) = created_with_dead_letter_exchange {
            self.check(Right::Read, Resource::Queue(queue))?;
            self.check(Right::Write, Resource::Exchange(exchange))?;
        }
        Ok(())
    }

    /// RabbitMQ's checks for declaring (not passively) the exchange
    /// `exchange`: configure on it, and when it is being created with an
    /// alternate exchange, read on it and write on the alternate.
    pub fn check_exchange_declare(
        &self,
        exchange: &str,
        created_with_alternate: Option<&str>,
    ) -> AmqpResult<()> {
        self.check(Right::Configure, Resource::Exchange(exchange))?;
        if let Some(alternate) = created_with_alternate {
            self.check(Right::Read, Resource::Exchange(exchange))?;
            self.check(Right::Write, Resource::Exchange(alternate))?;
        }
        Ok(())
    }

    /// RabbitMQ's checks for adding or removing a binding from the
    /// exchange `source` (the routing key is the topic check's, apart):
    /// write on the destination, read on the source.
    pub fn check_binding(&self, destination: Resource<'_>, source: &str) -> AmqpResult<()> {
        self.check(Right::Write, destination)?;
        self.check(Right::Read, Resource::Exchange(source))
    }
}

/// What is set for one (user, vhost).
#[derive(Debug, Clone, Default)]
struct Granted {
    permission: Option<Permission>,
    topics: BTreeMap<String, TopicPermission>,
}

#[derive(Debug, Default)]
struct Table {
    granted: BTreeMap<(String, String), Granted>,
    compiled: HashMap<(String, String), Arc<VhostAccess>>,
}

impl Table {
    /// Recompiles one (user, vhost) after a change. Patterns were checked
    /// as they run when set; should one still not compile, the user loses
    /// the vhost (closed, never open wider) and it is logged.
    fn recompile(&mut self, key: &(String, String)) {
        let compiled = self.granted.get(key).and_then(|granted| {
            let permission = granted.permission.as_ref()?;
            let (user, vhost) = key;
            let plain = |p: &str| Matcher::compile(p, None).ok();
            let topical = |p: &str| Matcher::compile(p, Some((user, vhost))).ok();
            let topics = granted
                .topics
                .iter()
                .map(|(exchange, t)| {
                    Some((
                        exchange.clone(),
                        CompiledTopic {
                            write: topical(&t.write)?,
                            read: topical(&t.read)?,
                        },
                    ))
                })
                .collect::<Option<HashMap<_, _>>>()?;
            Some(Arc::new(VhostAccess {
                user: user.clone(),
                vhost: vhost.clone(),
                configure: plain(&permission.configure)?,
                write: plain(&permission.write)?,
                read: plain(&permission.read)?,
                topics,
            }))
        });
        match compiled {
            Some(access) => self.compiled.insert(key.clone(), access),
            None => {
                if self
                    .granted
                    .get(key)
                    .is_some_and(|g| g.permission.is_some())
                {
                    tracing::error!(user = %key.0, vhost = %key.1, "a permission pattern does not compile: the user may not use the vhost");
                }
                self.compiled.remove(key)
            }
        };
        if self
            .granted
            .get(key)
            .is_some_and(|g| g.permission.is_none() && g.topics.is_empty())
        {
            self.granted.remove(key);
        }
    }
}

/// Every user's permissions, shared by the broker's channels and its
/// administration.
#[derive(Debug, Default)]
pub struct Permissions {
    table: RwLock<Table>,
    generation: AtomicU64,
}

fn key(user: &str, vhost: &str) -> (String, String) {
    (user.to_owned(), vhost.to_owned())
}

impl Permissions {
    fn read(&self) -> std::sync::RwLockReadGuard<'_, Table> {
        self.table.read().unwrap_or_else(|e| e.into_inner())
    }

    fn change(&self, key: (String, String), edit: impl FnOnce(&mut Granted)) {
        let mut table = self.table.write().unwrap_or_else(|e| e.into_inner());
        edit(table.granted.entry(key.clone()).or_default());
        table.recompile(&key);
        self.generation.fetch_add(1, Ordering::Release);
    }

    /// Sets `user`'s permission on `vhost` (RabbitMQ's `set_permissions`).
    pub fn set(&self, user: &str, vhost: &str, permission: Permission) -> Result<(), PatternError> {
        permission.check()?;
        self.change(key(user, vhost), |g| g.permission = Some(permission));
        Ok(())
    }

    /// Removes `user`'s permission on `vhost` (`clear_permissions`).
    pub fn clear(&self, user: &str, vhost: &str) {
        self.change(key(user, vhost), |g| g.permission = None);
    }

    /// Sets `user`'s topic permission on `exchange` in `vhost`
    /// (`set_topic_permissions`).
    pub fn set_topic(
        &self,
        user: &str,
        vhost: &str,
        exchange: &str,
        permission: TopicPermission,
    ) -> Result<(), PatternError> {
        permission.check(user, vhost)?;
        self.change(key(user, vhost), |g| {
            g.topics.insert(exchange.to_owned(), permission);
        });
        Ok(())
    }

    /// Removes `user`'s topic permission on `exchange` in `vhost`
    /// (`clear_topic_permissions`).
    pub fn clear_topic(&self, user: &str, vhost: &str, exchange: &str) {
        self.change(key(user, vhost), |g| {
            g.topics.remove(exchange);
        });
    }

    /// What `user` may do in `vhost`; `None` when they may not open it.
    pub fn of(&self, user: &str, vhost: &str) -> Option<Arc<VhostAccess>> {
        self.read().compiled.get(&key(user, vhost)).cloned()
    }

    /// Whether `user` may open `vhost` (has a permission there).
    pub fn may_open(&self, user: &str, vhost: &str) -> bool {
        self.read().compiled.contains_key(&key(user, vhost))
    }

    /// Moves on every change.
    pub fn generation(&self) -> u64 {
        self.generation.load(Ordering::Acquire)
    }

    /// Every (user, vhost, permission), ordered by user then vhost.
    pub fn list(&self) -> Vec<(String, String, Permission)> {
        self.read()
            .granted
            .iter()
            .filter_map(|((user, vhost), g)| {
                Some((user.clone(), vhost.clone(), g.permission.clone()?))
            })
            .collect()
    }

    /// Every (user, vhost, exchange, topic permission).
    pub fn list_topics(&self) -> Vec<(String, String, String, TopicPermission)> {
        self.read()
            .granted
            .iter()
            .flat_map(|((user, vhost), g)| {
                g.topics.iter().map(move |(exchange, t)| {
                    (user.clone(), vhost.clone(), exchange.clone(), t.clone())
                })
            })
            .collect()
    }
}

/// A channel's view of its user's rights in its vhost, refreshed when the
/// permissions change.
#[derive(Debug)]
pub struct AccessView {
    permissions: Arc<Permissions>,
    user: String,
    vhost: String,
    seen: u64,
    current: Option<Arc<VhostAccess>>,
}

impl AccessView {
    /// The view of `user` in `vhost`.
    pub fn new(permissions: Arc<Permissions>, user: &str, vhost: &str) -> Self {
        let seen = permissions.generation();
        let current = permissions.of(user, vhost);
        AccessView {
            permissions,
            user: user.to_owned(),
            vhost: vhost.to_owned(),
            seen,
            current,
        }
    }

    /// The user's current rights; a user whose permission was cleared
    /// while connected is refused everything.
    pub fn current(&mut self) -> AmqpResult<&VhostAccess> {
        let now = self.permissions.generation();
        if now != self.seen {
            self.seen = now;
            self.current = self.permissions.of(&self.user, &self.vhost);
        }
        self.current.as_deref().ok_or_else(|| {
            AmqpError::access_refused(format_args!(
                "access to vhost '{}' refused for user '{}'",
                self.vhost, self.user
            ))
        })
    }

    /// Checks `right` on `resource` (see [`VhostAccess::check`]).
    pub fn check(&mut self, right: Right, resource: Resource<'_>) -> AmqpResult<()> {
        self.current()?.check(right, resource)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use leveret_protocol::ReplyCode;

    fn permission(configure: &str, write: &str, read: &str) -> Permission {
        Permission {
            configure: configure.into(),
            write: write.into(),
            read: read.into(),
        }
    }

    fn refused(result: AmqpResult<()>) -> String {
        let error = result.expect_err("refused");
        assert_eq!(error.code, ReplyCode::AccessRefused);
        error.text
    }

    #[cfg(feature = "regex")]
    #[test]
    fn patterns_match_anywhere_and_the_empty_one_matches_nothing() {
        let all = Permissions::default();
        all.set("u", "/", permission("pu", "", "^r\\.")).unwrap();
        let access = all.of("u", "/").unwrap();
        assert!(access
            .check(Right::Configure, Resource::Queue("a.pu.b"))
            .is_ok());
        assert!(access.check(Right::Read, Resource::Queue("r.x")).is_ok());
        assert!(access.check(Right::Read, Resource::Queue("x.r.x")).is_err());
        assert!(access.check(Right::Write, Resource::Queue("x")).is_err());
        assert_eq!(
            refused(access.check(Right::Write, Resource::Exchange(""))),
            "ACCESS_REFUSED - access to exchange 'amq.default' in vhost '/' refused for user 'u'"
        );
        assert!(all.of("u", "other").is_none());
        assert!(all.of("v", "/").is_none());
    }

    #[test]
    fn topic_permissions_expand_user_and_vhost_and_leave_other_exchanges_open() {
        let all = Permissions::default();
        all.set("r.1", "cell", Permission::full()).unwrap();
        all.set_topic(
            "r.1",
            "cell",
            "amq.topic",
            TopicPermission {
                write: "^{username}\\.{vhost}\\.".into(),
                read: "".into(),
            },
        )
        .unwrap();
        let access = all.of("r.1", "cell").unwrap();
        assert!(access
            .check_topic(Right::Write, "amq.topic", "r.1.cell.x")
            .is_ok());
        // The user name's dot is a dot, not any character.
        assert_eq!(
            refused(access.check_topic(Right::Write, "amq.topic", "rx1.cell.x")),
            "ACCESS_REFUSED - access to topic 'rx1.cell.x' in exchange 'amq.topic' in vhost 'cell' refused for user 'r.1'"
        );
        assert!(access.check_topic(Right::Read, "amq.topic", "a").is_err());
        assert!(access.check_topic(Right::Read, "amq.topic", "").is_ok());
        assert!(access.check_topic(Right::Write, "other", "any").is_ok());
    }

    /// The patterns matched as strings match exactly the names the regex
    /// engine matches, placeholders and escapes included.
    #[cfg(feature = "regex")]
    #[test]
    fn literal_patterns_match_what_the_regex_engine_matches() {
        let patterns = [
            "",
            "^$",
            "^",
            "^.*",
            "^mine",
            "^mine$",
            "^mine.*",
            "^mi\\.ne",
            "^a\\\\$",
            "^{username}\\.{vhost}\\.",
            "^{username}$",
            "^amq\\.gen-",
            "^é$",
            "^a b",
        ];
        let names = [
            "",
            "mine",
            "mine.q",
            "minE",
            "xmine",
            "mi.ne",
            "mixne",
            "a\\",
            "a",
            "r.1.cell.x",
            "rx1.cell.x",
            "r.1",
            "amq.gen-1",
            "é",
            "e\u{301}",
            "a b",
            "^mine",
        ];
        let variables = Some(("r.1", "cell"));
        for pattern in patterns {
            let literal = Matcher::literal(pattern, variables)
                .unwrap_or_else(|| panic!("{pattern:?} is a literal pattern"));
            let source = match pattern {
                "" => "^$".to_owned(),
                p => p
                    .replace("{username}", &regex::escape("r.1"))
                    .replace("{vhost}", &regex::escape("cell")),
            };
            let regex = regex::Regex::new(&source).unwrap();
            for name in names {
                assert_eq!(
                    literal.matches(name),
                    regex.is_match(name),
                    "{pattern:?} on {name:?}"
                );
            }
        }
        for needs_the_engine in ["^a\\.*", "^a|b", "^a+$", "mine", "^(?i)a", "^a\\$", "^a\\"] {
            assert!(
                Matcher::literal(needs_the_engine, variables).is_none(),
                "{needs_the_engine:?}"
            );
        }
    }

    #[cfg(not(feature = "regex"))]
    #[test]
    fn without_the_regex_engine_only_literal_patterns_are_taken() {
        let all = Permissions::default();
        all.set("u", "/", permission("^mine", "^mine$", ""))
            .unwrap();
        let refused = all
            .set("u", "/", permission("^mine|^yours", ".*", ".*"))
            .unwrap_err();
        assert!(refused.reason.contains("`regex` feature"), "{refused}");
        let access = all.of("u", "/").expect("the first permission stays");
        assert!(access
            .check(Right::Configure, Resource::Queue("mine.q"))
            .is_ok());
        assert!(access
            .check(Right::Write, Resource::Queue("mine.q"))
            .is_err());
    }

    #[test]
    fn patterns_the_regex_engine_cannot_run_in_linear_time_are_refused_when_set() {
        let all = Permissions::default();
        for bad in ["(?=a)", "(a)\\1", "[", &format!("a{{{}}}", 1_000_000)] {
            assert!(
                all.set("u", "/", permission(bad, ".*", ".*")).is_err(),
                "{bad}"
            );
        }
        assert!(all.of("u", "/").is_none(), "nothing half set");
    }

    #[cfg(feature = "regex")]
    #[test]
    fn a_topic_pattern_is_checked_with_the_names_it_will_run_with() {
        let all = Permissions::default();
        let long = "u".repeat(255);
        all.set(&long, "/", Permission::full()).unwrap();
        // {username} repeated 500 times: small with a placeholder, far over
        // the size limit with a 255-byte name.
        let pattern = "^(?:{username}){500}".to_owned();
        assert!(check_pattern(&pattern).is_ok(), "passes with placeholders");
        let topic = TopicPermission {
            write: pattern,
            read: ".*".into(),
        };
        assert!(all.set_topic(&long, "/", "amq.topic", topic).is_err());
        let access = all.of(&long, "/").expect("the permission stays");
        assert!(
            !access.has_topic_permissions(),
            "the refused topic permission was not recorded half-way"
        );
    }

    #[test]
    fn declaring_and_binding_need_rabbitmqs_rights() {
        let all = Permissions::default();
        all.set("u", "/", permission("^mine", "^mine", "^mine"))
            .unwrap();
        let access = all.of("u", "/").unwrap();
        assert!(access.check_queue_declare("mine.q", None).is_ok());
        assert!(access
            .check_queue_declare("mine.q", Some("mine.dlx"))
            .is_ok());
        // Creating with a dead-letter exchange needs write on it.
        assert!(access
            .check_queue_declare("mine.q", Some("amq.fanout"))
            .is_err());
        assert!(access.check_queue_declare("other", None).is_err());
        assert!(access.check_exchange_declare("mine.x", None).is_ok());
        assert!(access
            .check_exchange_declare("mine.x", Some("amq.direct"))
            .is_err());
        // Write on the destination, read on the source.
        assert!(access
            .check_binding(Resource::Queue("mine.q"), "mine.x")
            .is_ok());
        assert!(access
            .check_binding(Resource::Queue("mine.q"), "amq.direct")
            .is_err());
        assert!(access
            .check_binding(Resource::Exchange("amq.direct"), "mine.x")
            .is_err());
    }

    #[test]
    fn a_view_follows_changes_and_a_cleared_user_is_refused() {
        let all = Arc::new(Permissions::default());
        all.set("u", "/", permission("", "", "")).unwrap();
        let mut view = AccessView::new(Arc::clone(&all), "u", "/");
        assert!(view.check(Right::Read, Resource::Queue("q")).is_err());
        all.set("u", "/", Permission::full()).unwrap();
        assert!(view.check(Right::Read, Resource::Queue("q")).is_ok());
        all.clear("u", "/");
        assert_eq!(
            refused(view.check(Right::Read, Resource::Queue("q"))),
            "ACCESS_REFUSED - access to vhost '/' refused for user 'u'"
        );
        assert!(all.list().is_empty());
    }
}
