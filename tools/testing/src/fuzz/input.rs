//! What a harness feeds its parser, and what one input did.

#[derive(Debug)]
pub(crate) struct Seed {
    /// What the bytes are: a dataset file name, or a file name whose extension says the kind.
    pub(crate) name: String,
    pub(crate) bytes: Vec<u8>,
}

/// What one input did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// The parser accepted it (and everything downstream ran).
    Accepted,
    /// The parser returned an error.
    Rejected,
}
