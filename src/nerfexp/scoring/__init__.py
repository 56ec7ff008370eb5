"""Scoring rendered images: PSNR and SSIM, LPIPS, each test image scored under its protocol, what an evaluated
image measures, and when a render counts as nothing."""
