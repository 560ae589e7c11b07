//! Remote datasets against servers that misbehave (feature `remote`): a scripted HTTP
//! server on loopback serves the fixture dataset and, where asked, redirects elsewhere or
//! answers a small range with a huge body. Each case ends quickly with an error naming the
//! cause, or succeeds where the user allowed it.
#![cfg(feature = "remote")]

mod support;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use citystream_dataset::remote::{open_dataset, RemoteOptions};
use citystream_dataset::{MANIFEST_FILE, PACK_HEADER_BYTES};

/// What the server does with a request for `path`.
#[derive(Clone, Debug)]
enum Behaviour {
    /// Serve the file (HEAD and ranges too).
    Serve,
    /// Answer 302 with this `Location`.
    Redirect(String),
    /// Answer GETs of ranges from this offset on with 206 and `Content-Length: 4 GiB`, then
    /// zeros until the client hangs up; serve the rest.
    HugeFrom(u64),
    /// Never answer GETs of ranges from this offset on (keep the connection open).
    SilentFrom(u64),
}

/// Serves `root` on a loopback port until the test ends; `rule` picks each request's answer.
fn serve(root: PathBuf, rule: impl Fn(&str) -> Behaviour + Send + Sync + 'static) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
    let address = format!("http://{}", listener.local_addr().expect("address"));
    let rule = Arc::new(rule);
    std::thread::spawn(move || {
        for stream in listener.incoming().flatten() {
            let (root, rule) = (root.clone(), Arc::clone(&rule));
            std::thread::spawn(move || {
                let _ = answer(stream, &root, rule.as_ref());
            });
        }
    });
    address
}

/// Answers the requests of one connection.
fn answer(stream: TcpStream, root: &Path, rule: &dyn Fn(&str) -> Behaviour) -> std::io::Result<()> {
    let mut reader = BufReader::new(stream.try_clone()?);
    let mut out = stream;
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line)? == 0 {
            return Ok(());
        }
        let mut parts = line.split_whitespace();
        let (method, path) = (
            parts.next().unwrap_or("").to_owned(),
            parts.next().unwrap_or("/").to_owned(),
        );
        let mut range = None;
        loop {
            let mut header = String::new();
            reader.read_line(&mut header)?;
            if header.trim().is_empty() {
                break;
            }
            if let Some((name, value)) = header.split_once(':') {
                if name.eq_ignore_ascii_case("range") {
                    range = value.trim().strip_prefix("bytes=").and_then(|r| {
                        let (a, b) = r.split_once('-')?;
                        Some((a.parse::<u64>().ok()?, b.parse::<u64>().ok()?))
                    });
                }
            }
        }
        match rule(&path) {
            Behaviour::Redirect(to) => {
                write!(out, "HTTP/1.1 302 Found\r\nLocation: {to}\r\nContent-Length: 0\r\n\r\n")?;
            }
            Behaviour::HugeFrom(from) if method == "GET" && range.is_some_and(|(start, _)| start >= from) => {
                // A 206 that claims the range asked for, with a body far longer. (A body
                // without a length is refused by `object_store` itself.)
                let (start, end) = range.unwrap_or((0, 0));
                write!(
                    out,
                    "HTTP/1.1 206 Partial Content\r\nContent-Range: bytes {start}-{end}/*\r\nContent-Length: {}\r\n\r\n",
                    4u64 << 30
                )?;
                let zeros = vec![0u8; 1 << 16];
                // Until the client hangs up (at most the 4 GiB declared).
                for _ in 0..(1u64 << 16) {
                    out.write_all(&zeros)?;
                }
                return Ok(());
            }
            Behaviour::SilentFrom(from) if method == "GET" && range.is_some_and(|(start, _)| start >= from) => {
                // Read what the client sends until it gives up.
                let mut sink = [0u8; 4096];
                while matches!(reader.read(&mut sink), Ok(n) if n > 0) {}
                return Ok(());
            }
            _ => serve_file(&mut out, root, &method, &path, range)?,
        }
    }
}

fn serve_file(
    out: &mut TcpStream,
    root: &Path,
    method: &str,
    path: &str,
    range: Option<(u64, u64)>,
) -> std::io::Result<()> {
    let Ok(mut file) = std::fs::File::open(root.join(path.trim_start_matches('/'))) else {
        return write!(out, "HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n");
    };
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes)?;
    let (status, body) = match range {
        Some((start, end)) => {
            let end = end.min(bytes.len() as u64 - 1);
            ("206 Partial Content", bytes[start as usize..=end as usize].to_vec())
        }
        None => ("200 OK", bytes.clone()),
    };
    let content_range = range.map_or(String::new(), |(start, _)| {
        format!(
            "Content-Range: bytes {start}-{}/{}\r\n",
            start + body.len() as u64 - 1,
            bytes.len()
        )
    });
    write!(
        out,
        "HTTP/1.1 {status}\r\nContent-Length: {}\r\n{content_range}Accept-Ranges: bytes\r\n\r\n",
        body.len()
    )?;
    if method != "HEAD" {
        out.write_all(&body)?;
    }
    Ok(())
}

/// Few retries and a short timeout: a refusal must not wait for them anyway.
fn options() -> RemoteOptions {
    RemoteOptions {
        retries: 1,
        timeout: Duration::from_secs(10),
        ..RemoteOptions::default()
    }
}

#[test]
fn a_redirect_to_another_origin_is_refused_unless_allowed() {
    let fixture = support::write_fixture("remote-redirect");
    let elsewhere = serve(fixture.dir.clone(), |_| Behaviour::Serve);
    let target = elsewhere.clone();
    let redirecting = serve(fixture.dir.clone(), move |path| {
        Behaviour::Redirect(format!("{target}{path}"))
    });
    let started = Instant::now();
    let error = open_dataset(&format!("{redirecting}/"), &options()).expect_err("refused");
    let message = error.to_string();
    assert!(message.contains("another origin"), "{message}");
    assert!(message.contains(&elsewhere), "{message}");
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "took {:?}",
        started.elapsed()
    );
    // Allowed, the data is the other origin's.
    let allowed = RemoteOptions {
        follow_redirects: true,
        ..options()
    };
    let dataset = open_dataset(&format!("{redirecting}/"), &allowed).expect("followed");
    assert_eq!(dataset.textures.len() as usize, fixture.textures.len());
}

#[test]
fn a_redirect_within_the_origin_is_followed() {
    let fixture = support::write_fixture("remote-redirect-within");
    // `/city/…` redirects to the same path without the prefix, on the same server.
    let origin = serve(fixture.dir.clone(), |path| match path.strip_prefix("/city") {
        Some(rest) => Behaviour::Redirect(rest.to_owned()),
        None => Behaviour::Serve,
    });
    let dataset = open_dataset(&format!("{origin}/city/"), &options()).expect("followed within the origin");
    assert_eq!(dataset.textures.len() as usize, fixture.textures.len());
}

#[test]
fn a_huge_answer_to_the_manifest_is_refused_unread() {
    let fixture = support::write_fixture("remote-huge-manifest");
    let server = serve(fixture.dir.clone(), |path| {
        if path.ends_with(MANIFEST_FILE) {
            Behaviour::HugeFrom(0)
        } else {
            Behaviour::Serve
        }
    });
    let started = Instant::now();
    let message = open_dataset(&format!("{server}/"), &options())
        .expect_err("refused")
        .to_string();
    assert!(
        message.contains("32 bytes with 4294967296: refused unread"),
        "{message}"
    );
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "took {:?}",
        started.elapsed()
    );
}

#[test]
fn a_huge_answer_to_a_mip_range_fails_that_read() {
    let fixture = support::write_fixture("remote-huge-mip");
    // The pack's header and the first texture's mips are served; later ranges answer hugely.
    let first_texture_end = PACK_HEADER_BYTES + fixture.textures[0].mips.iter().map(Vec::len).sum::<usize>() as u64;
    let server = serve(fixture.dir.clone(), move |path| {
        if path.ends_with("textures.pack") {
            Behaviour::HugeFrom(first_texture_end)
        } else {
            Behaviour::Serve
        }
    });
    let started = Instant::now();
    let dataset = open_dataset(&format!("{server}/"), &options()).expect("the header is served");
    let mut bytes = Vec::new();
    dataset
        .textures
        .read_mip(0, 0, &mut bytes)
        .expect("the first texture is served");
    assert_eq!(bytes, fixture.textures[0].mips[0]);
    let message = dataset
        .textures
        .read_mip(1, 0, &mut bytes)
        .expect_err("a mip answered with 4 GiB")
        .to_string();
    assert!(message.contains("with 4294967296: refused unread"), "{message}");
    assert!(
        started.elapsed() < Duration::from_secs(10),
        "took {:?}",
        started.elapsed()
    );
}

#[test]
fn a_server_that_stops_answering_fails_reads_within_one_retry_chain() {
    let fixture = support::write_fixture("remote-silent-mips");
    let server = serve(fixture.dir.clone(), |path| {
        if path.ends_with("textures.pack") {
            Behaviour::SilentFrom(PACK_HEADER_BYTES)
        } else {
            Behaviour::Serve
        }
    });
    let options = RemoteOptions {
        retries: 1,
        timeout: Duration::from_secs(1),
        initial_backoff: Duration::from_millis(10),
        ..RemoteOptions::default()
    };
    let dataset = open_dataset(&format!("{server}/"), &options).expect("the small files are served");
    let mut bytes = Vec::new();
    // The first read waits out its timeout and retry.
    let started = Instant::now();
    dataset.textures.read_mip(0, 0, &mut bytes).expect_err("no answer");
    let first = started.elapsed();
    assert!(
        first >= Duration::from_secs(1) && first < Duration::from_secs(10),
        "first read took {first:?}"
    );
    // Later reads fail at once, naming the silence.
    let started = Instant::now();
    let message = dataset
        .textures
        .read_mip(1, 0, &mut bytes)
        .expect_err("no answer")
        .to_string();
    assert!(
        started.elapsed() < Duration::from_millis(500),
        "took {:?}",
        started.elapsed()
    );
    assert!(
        message.contains("no answer from") && message.contains("unanswered"),
        "{message}"
    );
}
