//! `citystream bind-replay` refuses logs it cannot replay safely (the flythrough's tests
//! replay the logs of its flights).

mod cli_support;

use cli_support::{citystream, fresh_dir, stderr};

/// Logs bind-replay cannot replay safely are refused before anything is read past:
/// an image of a format the cache does not bind (its copies would be sized wrong), and
/// a log that is no regular file (a device would be read without end).
#[test]
fn a_log_of_a_foreign_format_or_a_device_file_is_refused() {
    let dir = fresh_dir("bind_replay", "refusals");
    // R32G32B32A32_SFLOAT (109): 16 bytes a texel, one 4096² copy.
    let foreign = dir.join("rgba32f.log");
    std::fs::write(
        &foreign,
        "citystream-bind-log 2\nimage 0 4096 4096 1 13 109 128 128 65536 13 0 0\nchunk 0 65536\ncopy 0 0 0 0 0 4096 4096\n",
    )
    .expect("write");
    let refused = citystream(&["bind-replay", foreign.to_str().expect("utf-8")]);
    assert!(!refused.status.success(), "a foreign format replayed");
    assert!(
        stderr(&refused).contains("R32G32B32A32_SFLOAT") && stderr(&refused).contains("not one the cache binds"),
        "{}",
        stderr(&refused)
    );
    let zero = citystream(&["bind-replay", "/dev/zero"]);
    assert!(!zero.status.success(), "/dev/zero replayed");
    assert!(stderr(&zero).contains("not a regular file"), "{}", stderr(&zero));
}
