"""Measures every stage shares: image and face quality (quality: PSNR, SSIM, LPIPS, dlib), the trivial baselines
(baselines) and the scores beside them (scoring), statistics over seeds (seeds), point-set alignment (alignment)."""
