//! # occ-model
//!
//! SparseOcc (paper Sec. 3), SparseOcc++ (paper Sec. 4) and the dense baseline, in burn: one folder
//! per model, one file per stage, each `XConfig::init(&device) -> X` with a documented `forward`.
//!
//! Shared vocabulary: [`batch::Batch`] (images, cameras, targets) goes in, [`output::ModelOutput`]
//! (sparse voxel logits, losses, per-stage statistics) comes out; [`occnet::OccNet`] is the whole
//! network (image encoder + one of the three models + losses) that training and inference use.
//!
//! Every model is generic over `B: ModelBackend`, a burn backend extension (like occ-sparse's
//! `SparseConvBackend`, its supertrait) whose default methods run the portable burn ops and whose
//! `NdArray` / `Autodiff<NdArray>` implementations run the CPU fast paths of [`kernels`].
//!
//! ## Paper section → path
//!
//! | paper | stage | path |
//! |---|---|---|
//! | Sec. 5.1 | image backbone (ResNet) | [`encoder::backbone`] |
//! | Sec. 5.1 | FPN neck, the image encoder | [`encoder::fpn`] |
//! | — | pretrained torchvision weights | [`encoder::weights`] |
//! | Sec. 3.1 | LSS view transform (SparseOcc and the dense baseline) | [`lss`] |
//! | Sec. 3 | SparseOcc assembly | [`sparseocc`] |
//! | Sec. 3.2 | sparse latent propagator | [`sparseocc::propagator`] |
//! | Sec. 3.3 | sparse feature pyramid, interpolation decoder | [`sparseocc::pyramid`] |
//! | Sec. 3.4 | sparse transformer (mask) head | [`sparseocc::mask_head`] |
//! | Sec. 3.5 | bipartite matching | [`sparseocc::hungarian`] |
//! | Sec. 4 | SparseOcc++ assembly, its targets and losses | [`sparseocc_pp`] |
//! | Sec. 4.2 | sparse anchor voxel generation | [`sparseocc_pp::anchors`] |
//! | Sec. 4.2 | deformable cross attention (DCA) | [`sparseocc_pp::dca`], sampling in [`sample`] |
//! | Sec. 4.2 | scene completion field (SCF) heads | [`sparseocc_pp::scf_head`] |
//! | Sec. 4.2, Alg. 1 | geometry-guided propagation | [`sparseocc_pp::propagation`] |
//! | Sec. 4.3 | lightweight sparse U-Net | [`sparseocc_pp::unet`] |
//! | — (not in the paper) | SparseOcc++ options and diagnostics | [`sparseocc_pp::extras`] |
//! | Table "all modules disabled" | dense baseline | [`dense`] |
//! | docs/formats.md §2.6 | label conventions and downsampling rules | the `occ-labels` crate; batch targets in `targets` |
//! | Sec. 3.5, 4.4 | losses (CE, Lovasz, scene-class affinity, mask, depth) | [`loss`] |
//! | — | compute kernels: [`ModelBackend`] (portable burn ops; CPU fast paths for image convs and DCA sampling) | [`kernels`] |
//! | — | per-stage timing for `sparseocc bench` | [`profile`] |

pub mod batch;
pub mod dense;
pub mod encoder;
pub mod error;
pub mod kernels;
pub mod loss;
pub mod lss;
pub mod network;
pub mod occnet;
pub mod output;
pub mod profile;
pub mod sample;
pub mod sparseocc;
pub mod sparseocc_pp;
mod targets;

pub use batch::{Batch, CameraInput};
pub use error::ModelError;
pub use kernels::ModelBackend;
pub use network::OccNetwork;
pub use occnet::{load_checked, ModelKind, Network, NetworkVariant, OccNet, OccNetConfig};
pub use output::ModelOutput;
