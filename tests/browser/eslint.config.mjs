// ESLint for the dashboard (ui/: ES modules in the browser) and its browser tests (Node ES
// modules). scripts/ci-browser.sh copies this file beside its node_modules in
// target/browser-tests/ and runs it from the repository root: `eslint -c ... ui tests/browser`.
import js from '@eslint/js';
import globals from 'globals';

export default [
  js.configs.recommended,
  {
    linterOptions: { reportUnusedDisableDirectives: 'error' },
    rules: {
      // `const { id, ...settings } = e` leaves out what it names: not unused.
      'no-unused-vars': ['error', { ignoreRestSiblings: true }],
      eqeqeq: ['error', 'smart'],
      'array-callback-return': 'error',
      'no-constructor-return': 'error',
      'no-promise-executor-return': 'error',
      'no-self-compare': 'error',
      'no-template-curly-in-string': 'error',
      'no-unmodified-loop-condition': 'error',
      'no-unreachable-loop': 'error',
      'no-var': 'error',
      'prefer-const': 'error',
    },
  },
  {
    files: ['ui/**/*.js'],
    languageOptions: { globals: globals.browser },
    rules: {
      // app.js is the entry point only: importing it again would make a module circle.
      'no-restricted-imports': [
        'error',
        {
          patterns: [
            {
              regex: '(^|/)app\\.js$',
              message: 'app.js is the entry point; shared helpers live in api.js, dom.js and format.js.',
            },
          ],
        },
      ],
    },
  },
  {
    files: ['tests/browser/**/*.mjs'],
    // Node, plus the browser's globals in the callbacks Playwright runs in the page (`page.evaluate`).
    languageOptions: { globals: { ...globals.node, ...globals.browser } },
  },
];
