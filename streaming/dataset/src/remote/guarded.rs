//! The HTTP client of every remote store, guarded against servers that misbehave: reqwest
//! with the store's timeouts, redirects followed only within the origin a request was
//! sent to (unless the user allowed others), and every answer to a range request read no
//! further than the range asked for: a `Content-Length` beyond it is refused before the
//! body is read, and a body that runs past it (chunked, or lying) fails as the excess
//! arrives. Both refusals are not retried: the server would answer the same again.

use std::error::Error;
use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use http_body_util::{BodyExt, LengthLimitError, Limited};
use object_store::client::{
    HttpClient, HttpConnector, HttpError, HttpErrorKind, HttpRequest, HttpResponse, HttpResponseBody, HttpService,
};
use object_store::ClientOptions;

/// Redirects within the dataset URL's origin followed at most, per request.
pub const MAX_REDIRECTS: usize = 10;

/// Builds the guarded client (`object_store`'s own client options are replaced by these).
#[derive(Debug)]
pub(super) struct GuardedConnector {
    pub(super) timeout: Duration,
    pub(super) connect_timeout: Duration,
    /// Follow redirects to another origin too.
    pub(super) follow_redirects: bool,
    /// A query string every request carries (`token=…` of a hosted tileset's URL), for
    /// HTTP stores; `None` without one.
    pub(super) query: Option<String>,
}

impl HttpConnector for GuardedConnector {
    fn connect(&self, _options: &ClientOptions) -> object_store::Result<HttpClient> {
        let follow_redirects = self.follow_redirects;
        let policy = reqwest::redirect::Policy::custom(move |attempt| {
            let within_origin = attempt
                .previous()
                .first()
                .is_some_and(|first| same_origin(first, attempt.url()));
            if attempt.previous().len() > MAX_REDIRECTS {
                attempt.error(format!("more than {MAX_REDIRECTS} redirects"))
            } else if within_origin || follow_redirects {
                attempt.follow()
            } else {
                // Handed back as the response: the service below names it.
                attempt.stop()
            }
        });
        let client = reqwest::Client::builder()
            .timeout(self.timeout)
            .connect_timeout(self.connect_timeout)
            .redirect(policy)
            .build()
            .map_err(|e| object_store::Error::Generic {
                store: "HTTP",
                source: Box::new(e),
            })?;
        Ok(HttpClient::new(GuardedService {
            client,
            query: self.query.clone(),
        }))
    }
}

/// Scheme, host and port alike.
fn same_origin(a: &reqwest::Url, b: &reqwest::Url) -> bool {
    a.scheme() == b.scheme() && a.host_str() == b.host_str() && a.port_or_known_default() == b.port_or_known_default()
}

/// What a guarded request refused, in words that name the server's answer.
#[derive(Debug)]
struct Refused(String);

impl std::fmt::Display for Refused {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl Error for Refused {}

fn refused(message: String) -> HttpError {
    // `Decode` is never retried.
    HttpError::new(HttpErrorKind::Decode, Refused(message))
}

#[derive(Debug)]
struct GuardedService {
    client: reqwest::Client,
    query: Option<String>,
}

/// `request` with `query` added to its URI's own query, if any.
fn with_query(mut request: HttpRequest, query: Option<&str>) -> Result<HttpRequest, HttpError> {
    let Some(query) = query else {
        return Ok(request);
    };
    let uri = request.uri().to_string();
    let joined = if uri.contains('?') {
        format!("{uri}&{query}")
    } else {
        format!("{uri}?{query}")
    };
    *request.uri_mut() = joined
        .parse()
        .map_err(|e| refused(format!("{uri} with the query {query:?}: {e}")))?;
    Ok(request)
}

/// The bytes a `Range: bytes=a-b` header asks for.
fn range_length(request: &HttpRequest) -> Option<u64> {
    let value = request.headers().get("range")?.to_str().ok()?;
    let (start, end) = value.trim().strip_prefix("bytes=")?.split_once('-')?;
    let (start, end): (u64, u64) = (start.trim().parse().ok()?, end.trim().parse().ok()?);
    end.checked_sub(start)?.checked_add(1)
}

impl HttpService for GuardedService {
    fn call<'life0, 'async_trait>(
        &'life0 self,
        request: HttpRequest,
    ) -> Pin<Box<dyn Future<Output = Result<HttpResponse, HttpError>> + Send + 'async_trait>>
    where
        'life0: 'async_trait,
        Self: 'async_trait,
    {
        Box::pin(async move {
            let request = with_query(request, self.query.as_deref())?;
            let asked = range_length(&request);
            let url = request.uri().to_string();
            let response = self.client.call(request).await?;
            if response.status().is_redirection() {
                let to = response
                    .headers()
                    .get("location")
                    .and_then(|l| l.to_str().ok())
                    .unwrap_or("(no location)");
                return Err(refused(format!(
                    "{url} redirects to {to}, another origin: refused (allow with --remote-follow-redirects \
                     or CITYSTREAM_REMOTE_FOLLOW_REDIRECTS=1)"
                )));
            }
            let Some(asked) = asked else {
                return Ok(response);
            };
            let (parts, body) = response.into_parts();
            let declared = parts
                .headers
                .get("content-length")
                .and_then(|l| l.to_str().ok())
                .and_then(|l| l.trim().parse::<u64>().ok());
            if let Some(declared) = declared.filter(|&d| d > asked) {
                return Err(refused(format!(
                    "{url} answered a request for {asked} bytes with {declared}: refused unread"
                )));
            }
            let limit = usize::try_from(asked).unwrap_or(usize::MAX);
            let body = Limited::new(body, limit).map_err(move |error| match error.downcast::<HttpError>() {
                Ok(error) => *error,
                Err(error) if error.is::<LengthLimitError>() => refused(format!(
                    "{url} sent more than the {asked} bytes asked for: read no further"
                )),
                Err(error) => HttpError::new(HttpErrorKind::Unknown, Refused(error.to_string())),
            });
            Ok(HttpResponse::from_parts(parts, HttpResponseBody::new(body)))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_lengths_are_read_from_the_header() {
        let request = |range: &str| {
            let mut request = HttpRequest::new(Vec::<u8>::new().into());
            request.headers_mut().insert("range", range.parse().expect("header"));
            request
        };
        assert_eq!(range_length(&request("bytes=0-31")), Some(32));
        assert_eq!(range_length(&request("bytes=100-100")), Some(1));
        assert_eq!(range_length(&request("bytes=5-4")), None);
        assert_eq!(range_length(&request("bytes=0-")), None);
        assert_eq!(range_length(&request("items=0-1")), None);
        assert_eq!(range_length(&HttpRequest::new(Vec::<u8>::new().into())), None);
    }

    #[test]
    fn origins_compare_scheme_host_and_port() {
        let url = |text: &str| reqwest::Url::parse(text).expect("url");
        assert!(same_origin(&url("http://a:80/x"), &url("http://a/y")));
        assert!(!same_origin(&url("http://a/x"), &url("http://b/x")));
        assert!(!same_origin(&url("http://a/x"), &url("https://a/x")));
        assert!(!same_origin(&url("http://a:8080/x"), &url("http://a:8081/x")));
    }
}
