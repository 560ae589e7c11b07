#version 460

// Depth pre-pass of the feedback: writes depth only, so the feedback pass
// after it runs for the nearest surface alone.
void main() {
}
