// Headless Chromium as the browser tests launch it.
import { chromium } from 'playwright-core';

/** Launches headless Chromium ($CHROMIUM, else Debian's /usr/bin/chromium), quiet and offline. */
export function launchChromium() {
  return chromium.launch({
    executablePath: process.env.CHROMIUM ?? '/usr/bin/chromium',
    args: [
      '--headless',
      '--no-sandbox',
      '--disable-gpu',
      '--disable-quic',
      '--no-first-run',
      '--disable-background-networking',
      '--disable-component-update',
      '--disable-sync',
    ],
  });
}
