"""How renders are judged and shown: PSNR and SSIM (``image``, the one ``psnr``), LPIPS-VGG (``lpips``) and the
contact sheets with their depth colouring (``sheets``).

Public names: ``image.psnr``, ``image.ssim``, ``lpips.LPIPS``, ``sheets.depth_png``.
"""
