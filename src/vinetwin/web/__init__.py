"""The Viser authoring app (`vinetwin web`, docs/web.md): `session` holds the editing logic
(testable without a browser), `app` binds it to the page, `server` starts it (`serve`,
`serve_folder`); `display` decimates the vine for the page, `browser` drives headless Chromium
for the tests and the benchmark, `config` holds its settings."""
