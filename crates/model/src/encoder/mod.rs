//! The image encoder both models share (paper Sec. 5.1: a ResNet backbone and an FPN neck), and the
//! loader of pretrained torchvision weights.
//!
//! - [`backbone`]: ResNet-18/34/50 in torchvision's module layout.
//! - [`fpn`]: the FPN neck and [`fpn::ImageEncoder`] (ResNet + FPN → multi-scale features).
//! - [`weights`]: PyTorch `.pth` / `.safetensors` checkpoints into burn modules.

pub mod backbone;
pub mod fpn;
pub mod weights;
