// A screenshot of a splat viewer page in headless Chromium (software WebGL), once the scene has rendered:
// the SuperSplat viewer (window.captureFrame appears on its first frame) or spark.html (window.framesRendered).
// Used by scripts/checks/viewer_check.py; see docs/model.md "Opening a scene in a viewer".
//   node scripts/checks/viewer/screenshot.mjs URL OUT.png WIDTH HEIGHT [CHROMIUM]
import { chromium } from 'playwright-core';

const [url, out, width, height, executablePath = '/usr/bin/chromium'] = process.argv.slice(2);
if (!url || !out || !width || !height) {
    console.error('usage: node screenshot.mjs URL OUT.png WIDTH HEIGHT [CHROMIUM]');
    process.exit(2);
}
const browser = await chromium.launch({
    executablePath,
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run', '--disable-background-networking',
           '--disable-component-update', '--disable-sync', '--use-angle=swiftshader', '--enable-unsafe-swiftshader']
});
try {
    const page = await browser.newPage({ viewport: { width: Number(width), height: Number(height) }, deviceScaleFactor: 1 });
    page.on('pageerror', (e) => console.error('[page error]', e.message));
    page.on('console', (m) => console.error('[page]', m.text()));
    await page.goto(url);
    await page.waitForFunction(() => typeof window.captureFrame === 'function' || (window.framesRendered ?? 0) > 30,
                               null, { timeout: 180000 });
    await page.waitForTimeout(3000); // a few more frames: the splat sort settles
    await page.screenshot({ path: out });
} finally {
    await browser.close();
}
