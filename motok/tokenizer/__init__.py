"""motok.tokenizer"""
