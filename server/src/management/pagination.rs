//! RabbitMQ's pagination of list endpoints (queues, exchanges, vhosts,
//! connections, channels). With `page`, a listing answers one page:
//! `{"filtered_count", "item_count", "items", "page", "page_count",
//! "page_size", "total_count"}`; `page_size` is 100 by default and at most
//! [`MAX_PAGE_SIZE`]; `name` keeps the objects whose name contains it
//! (ignoring case), or matches it as a regular expression with
//! `use_regex=true`; `sort` orders by a field of the objects (dotted for a
//! nested one, `message_stats.publish`) and `sort_reverse=true` reverses
//! the order. Without `page` a listing is the plain array of everything,
//! `name` and `sort` ignored, as in RabbitMQ. Bad values are RabbitMQ's
//! 400s.
//!
//! Only the page's objects are written out: the others are filtered by
//! name, and sorted by one field each, one at a time (with a yield every
//! [`CHUNK`]), so a page of 100k queues costs memory for the page and one
//! sort key per queue, not for every queue's JSON.

use super::api::ApiError;
use serde_json::{json, Value};
use std::cmp::Ordering;
use std::collections::HashMap;

/// RabbitMQ's largest page.
pub const MAX_PAGE_SIZE: usize = 500;
/// RabbitMQ's page size when none is given.
const DEFAULT_PAGE_SIZE: usize = 100;
/// Objects turned into sort keys between two yields.
const CHUNK: usize = 500;
/// The largest compiled `name` pattern, in bytes.
const PATTERN_SIZE_LIMIT: usize = 1 << 20;

/// How objects are kept by name.
#[derive(Debug)]
enum NameFilter {
    /// Contains this, ignoring case (lowercased).
    Contains(String),
    /// Matches this (ignoring case).
    Pattern(regex::Regex),
}

/// A listing's `page`, `page_size`, `name`, `use_regex`, `sort` and
/// `sort_reverse`.
#[derive(Debug)]
pub struct Pagination {
    page: usize,
    page_size: usize,
    name: Option<NameFilter>,
    /// A JSON pointer to the sort field.
    sort: Option<String>,
    reverse: bool,
}

fn invalid() -> ApiError {
    ApiError::bad_request("Pagination parameters are invalid")
}

impl Pagination {
    /// The pagination a query asks for; `None` without `page`.
    pub fn from_query(query: &HashMap<String, String>) -> Result<Option<Pagination>, ApiError> {
        let Some(page) = query.get("page") else {
            return Ok(None);
        };
        let number = |text: &str| text.trim().parse::<usize>().map_err(|_| invalid());
        let page = number(page)?;
        let page_size = query
            .get("page_size")
            .map_or(Ok(DEFAULT_PAGE_SIZE), |size| number(size))?;
        if page == 0 || page_size == 0 || page_size > MAX_PAGE_SIZE {
            return Err(ApiError {
                status: axum::http::StatusCode::BAD_REQUEST,
                error: "invalid_pagination_parameters",
                reason: format!(
                    "Invalid pagination parameters: page number {page}, page size {page_size}"
                ),
            });
        }
        let flag = |key: &str| query.get(key).is_some_and(|v| v == "true");
        let name = match query.get("name").filter(|name| !name.is_empty()) {
            None => None,
            Some(pattern) if flag("use_regex") => Some(NameFilter::Pattern(
                regex::RegexBuilder::new(pattern)
                    .case_insensitive(true)
                    .size_limit(PATTERN_SIZE_LIMIT)
                    .build()
                    .map_err(|_| invalid())?,
            )),
            Some(text) => Some(NameFilter::Contains(text.to_lowercase())),
        };
        let sort = query
            .get("sort")
            .filter(|field| !field.is_empty())
            .map(|field| format!("/{}", field.replace('.', "/")));
        Ok(Some(Pagination {
            page,
            page_size,
            name,
            sort,
            reverse: flag("sort_reverse"),
        }))
    }

    fn keeps(&self, name: &str) -> bool {
        match &self.name {
            None => true,
            Some(NameFilter::Contains(text)) => name.to_lowercase().contains(text.as_str()),
            Some(NameFilter::Pattern(regex)) => regex.is_match(name),
        }
    }

    /// One page of `items` (in the listing's order), each object's name
    /// read by `name` and its JSON written by `json`.
    pub async fn page_of<T>(
        &self,
        items: Vec<T>,
        name: impl Fn(&T) -> &str,
        json: impl Fn(&T) -> Value,
    ) -> Result<Value, ApiError> {
        let total = items.len();
        let mut kept: Vec<T> = items
            .into_iter()
            .filter(|item| self.keeps(name(item)))
            .collect();
        if let Some(pointer) = &self.sort {
            let mut keyed = Vec::with_capacity(kept.len());
            for (i, item) in kept.drain(..).enumerate() {
                let key = json(&item).pointer(pointer).cloned().unwrap_or(Value::Null);
                keyed.push((key, item));
                if i % CHUNK == CHUNK - 1 {
                    tokio::task::yield_now().await;
                }
            }
            keyed.sort_by(|(a, _), (b, _)| compare(a, b));
            kept = keyed.into_iter().map(|(_, item)| item).collect();
        }
        if self.reverse {
            kept.reverse();
        }
        let filtered = kept.len();
        let start = (self.page - 1) * self.page_size;
        if self.page > 1 && start >= filtered {
            return Err(ApiError {
                status: axum::http::StatusCode::BAD_REQUEST,
                error: "page_out_of_range",
                reason: format!(
                    "Page out of range, page: {} page size: {}, len: {filtered}",
                    self.page, self.page_size
                ),
            });
        }
        let shown: Vec<Value> = kept
            .iter()
            .skip(start)
            .take(self.page_size)
            .map(json)
            .collect();
        Ok(json!({
            "filtered_count": filtered,
            "item_count": shown.len(),
            "items": shown,
            "page": self.page,
            "page_count": filtered.div_ceil(self.page_size),
            "page_size": self.page_size,
            "total_count": total,
        }))
    }
}

/// Orders sort keys: numbers by value, strings and the rest by text,
/// missing fields first.
fn compare(a: &Value, b: &Value) -> Ordering {
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => x
            .as_f64()
            .partial_cmp(&y.as_f64())
            .unwrap_or(Ordering::Equal),
        (Value::String(x), Value::String(y)) => x.cmp(y),
        (Value::Null, Value::Null) => Ordering::Equal,
        (Value::Null, _) => Ordering::Less,
        (_, Value::Null) => Ordering::Greater,
        (x, y) => x.to_string().cmp(&y.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn query(pairs: &[(&str, &str)]) -> HashMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| (k.to_string(), v.to_string()))
            .collect()
    }

    fn names(page: &Value) -> Vec<&str> {
        page["items"]
            .as_array()
            .expect("items")
            .iter()
            .map(|item| item["name"].as_str().expect("name"))
            .collect()
    }

    fn objects() -> Vec<Value> {
        (1..=5)
            .map(|i| json!({"name": format!("pq{i}"), "messages": 10 - i}))
            .collect()
    }

    async fn page(pairs: &[(&str, &str)]) -> Result<Value, ApiError> {
        let pagination = Pagination::from_query(&query(pairs))?.expect("paged");
        pagination
            .page_of(
                objects(),
                |o: &Value| o["name"].as_str().unwrap_or(""),
                Value::clone,
            )
            .await
    }

    #[tokio::test]
    async fn pages_have_rabbitmqs_shape_and_counts() {
        let second = page(&[("page", "2"), ("page_size", "2")]).await.unwrap();
        assert_eq!(names(&second), ["pq3", "pq4"]);
        let mut shape = second.clone();
        shape["items"] = json!([]);
        assert_eq!(
            shape,
            json!({"filtered_count": 5, "item_count": 2, "items": [], "page": 2,
                   "page_count": 3, "page_size": 2, "total_count": 5})
        );
        assert_eq!(page(&[("page", "1")]).await.unwrap()["page_size"], 100);
        let regex = page(&[("page", "1"), ("name", "PQ[13]"), ("use_regex", "true")])
            .await
            .unwrap();
        assert_eq!(names(&regex), ["pq1", "pq3"]);
        assert_eq!(regex["filtered_count"], 2);
        assert_eq!(regex["total_count"], 5);
        let text = page(&[("page", "1"), ("name", "Q2")]).await.unwrap();
        assert_eq!(names(&text), ["pq2"]);
        let sorted = page(&[("page", "1"), ("sort", "messages")]).await.unwrap();
        assert_eq!(names(&sorted), ["pq5", "pq4", "pq3", "pq2", "pq1"]);
        let reversed = page(&[
            ("page", "1"),
            ("page_size", "2"),
            ("sort", "name"),
            ("sort_reverse", "true"),
        ])
        .await
        .unwrap();
        assert_eq!(names(&reversed), ["pq5", "pq4"]);
    }

    #[tokio::test]
    async fn bad_values_are_rabbitmqs_400s() {
        assert!(Pagination::from_query(&query(&[("name", "x")]))
            .unwrap()
            .is_none());
        for (pairs, error, reason) in [
            (
                &[("page", "abc")][..],
                "bad_request",
                "Pagination parameters are invalid",
            ),
            (
                &[("page", "1"), ("name", "("), ("use_regex", "true")],
                "bad_request",
                "Pagination parameters are invalid",
            ),
            (
                &[("page", "0"), ("page_size", "2")],
                "invalid_pagination_parameters",
                "Invalid pagination parameters: page number 0, page size 2",
            ),
            (
                &[("page", "1"), ("page_size", "501")],
                "invalid_pagination_parameters",
                "Invalid pagination parameters: page number 1, page size 501",
            ),
            (
                &[("page", "9"), ("page_size", "2")],
                "page_out_of_range",
                "Page out of range, page: 9 page size: 2, len: 5",
            ),
        ] {
            let refused = page(pairs).await.unwrap_err();
            assert_eq!(
                (
                    refused.status.as_u16(),
                    refused.error,
                    refused.reason.as_str()
                ),
                (400, error, reason)
            );
        }
        // An empty listing has a first page.
        let pagination = Pagination::from_query(&query(&[("page", "1")]))
            .unwrap()
            .unwrap();
        let empty = pagination
            .page_of(Vec::<Value>::new(), |_| "", Value::clone)
            .await
            .unwrap();
        assert_eq!(
            (empty["page_count"].clone(), empty["item_count"].clone()),
            (json!(0), json!(0))
        );
    }
}
