//! Files and the terminal: images in and out, atomic writes, progress bars, what the system says
//! about memory.

pub mod atomic;
pub mod image;
pub mod meminfo;
pub mod progress;
